//! Scenario validation from the user's side: every file in `topologies/` passes `canopy check`,
//! and broken scenarios are rejected with an error that names the file, the field and the
//! reason — both through the library (`Scenario::load` returning the right [`ScenarioError`])
//! and through the binary (`canopy check FILE` exits non-zero, its stderr names all three).
//!
//! The broken files are generated here from `topologies/tree-4.toml` by one textual edit each,
//! so every case differs from a valid scenario in exactly the way its name says.

use std::path::{Path, PathBuf};

use canopy_node::scenario::{Scenario, ScenarioError};

mod common;

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("node/ is inside the workspace")
        .to_path_buf()
}

/// `canopy check FILE`: (success, stdout, stderr).
fn check(file: &Path) -> (bool, String, String) {
    common::canopy(&["check".as_ref(), file.as_os_str()])
}

/// Every shipped scenario is valid: `canopy check` succeeds on it and `Scenario::load` accepts
/// it (and it is not trivially empty: it has vehicles).
#[test]
fn every_topology_passes_canopy_check() {
    let dir = root().join("topologies");
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .expect("topologies/ exists")
        .map(|e| e.expect("dir entry").path())
        .filter(|p| p.extension().is_some_and(|e| e == "toml"))
        .collect();
    files.sort();
    // The list: tree-4, central-4, chain-6, tree-8, bearing-only and seven outage
    // scenarios.
    assert!(files.len() >= 12, "only {} scenario files", files.len());
    for f in &files {
        let (ok, stdout, stderr) = check(f);
        assert!(ok, "canopy check {} failed:\n{stdout}{stderr}", f.display());
        assert!(
            stdout.contains("valid"),
            "{}: no verdict:\n{stdout}",
            f.display()
        );
        let s = Scenario::load(f).unwrap_or_else(|e| panic!("{}: {e}", f.display()));
        assert!(!s.vehicles.is_empty());
    }
}

/// The built-in default is tree-4.toml (the file says so).
#[test]
fn tree_4_is_the_builtin_default() {
    let mut s = Scenario::load(&root().join("topologies/tree-4.toml")).expect("loads");
    let mut d = Scenario::builtin_default();
    s.run.name = None;
    d.run.name = None;
    assert_eq!(s, d);
}

/// How a broken file must be rejected.
enum Expect {
    /// `ScenarioError::Invalid` with this field and a reason containing this text.
    Invalid(&'static str, &'static str),
    /// `ScenarioError::Parse` (schema: unknown field, missing field, wrong type, unknown
    /// variant) whose message contains both texts (the field and the reason).
    Parse(&'static str, &'static str),
}

struct Case {
    kind: &'static str,
    /// (text in tree-4.toml, replacement): the one edit that breaks it.
    edit: (&'static str, &'static str),
    expect: Expect,
}

fn cases() -> Vec<Case> {
    use Expect::{Invalid, Parse};
    const LINK_1_3: &str = "[[link]]\na = 1\nb = 3\ntransport = \"shm\"\n";
    vec![
        Case {
            kind: "cycle",
            edit: (
                LINK_1_3,
                "[[link]]\na = 1\nb = 3\n\n[[link]]\na = 1\nb = 2\n",
            ),
            expect: Invalid("link", "cycle"),
        },
        Case {
            kind: "unknown vehicle",
            edit: (LINK_1_3, "[[link]]\na = 1\nb = 9\n"),
            expect: Invalid("link[0].b", "node 9 is not a vehicle"),
        },
        Case {
            kind: "duplicate id",
            edit: ("id = 2\n", "id = 1\n"),
            expect: Invalid("vehicle[1].id", "already used"),
        },
        Case {
            kind: "bad number (probability out of range)",
            edit: ("rate_hz = 1.0 ", "gate_probability = 1.5\nrate_hz = 1.0 "),
            expect: Invalid("fusion.gate_probability", "must be in (0, 1)"),
        },
        Case {
            kind: "bad number (a non-positive correspondence bound)",
            edit: (
                "rate_hz = 1.0 ",
                "correspondence_max_sigma_m = 0.0\nrate_hz = 1.0 ",
            ),
            expect: Invalid("fusion.correspondence_max_sigma_m", "must be > 0"),
        },
        Case {
            kind: "bad number (a negative interval between radio deltas)",
            edit: ("rate_hz = 1.0 ", "radio_interval_s = -1.0\nrate_hz = 1.0 "),
            expect: Invalid("fusion.radio_interval_s", "must be in [0, 3600] s"),
        },
        Case {
            kind: "simulation-time delivery outside decentralized mode",
            edit: (
                "mode = \"decentralized\"",
                "mode = \"isolated\"\ndelivery = \"simulation_time\"",
            ),
            expect: Invalid("fusion.delivery", "decentralized mode"),
        },
        Case {
            kind: "bad number (zero feature count)",
            edit: ("features = { count = 400,", "features = { count = 0,"),
            expect: Invalid("world.features.count", "must be in 1..="),
        },
        Case {
            kind: "missing field",
            edit: (
                "[[vehicle]]\nid = 4\nname = \"uav4\"\n",
                "[[vehicle]]\nname = \"uav4\"\n",
            ),
            expect: Parse("id", "missing field"),
        },
        Case {
            kind: "simulated vehicle without a trajectory",
            edit: (
                "[[vehicle]]\nid = 4\nname = \"uav4\"\ntrajectory = ",
                "[[vehicle]]\nid = 4\nname = \"uav4\"\n# trajectory = ",
            ),
            expect: Invalid("vehicle[3].trajectory", "needs a trajectory"),
        },
        Case {
            kind: "port clash",
            edit: (
                "[[link]]\na = 2\nb = 3\ntransport = \"shm\"\n\n[[link]]\na = 3\nb = 4\ntransport = \"shm\"\n",
                "[[link]]\na = 2\nb = 3\ntransport = \"net\"\nlisten = \"tcp/127.0.0.1:7447\"\n\n\
                 [[link]]\na = 3\nb = 4\ntransport = \"net\"\nlisten = \"tcp/127.0.0.1:7447\"\n",
            ),
            expect: Invalid("link[2].listen", "port clash"),
        },
        Case {
            kind: "unknown transport",
            edit: (LINK_1_3, "[[link]]\na = 1\nb = 3\ntransport = \"pigeon\"\n"),
            expect: Parse("pigeon", "unknown variant"),
        },
        Case {
            kind: "unknown compression",
            edit: (
                "rate_hz = 1.0                 # fusion rounds per simulated second",
                "rate_hz = 1.0\ndelta_compression = \"gzip\"",
            ),
            expect: Parse("gzip", "unknown variant"),
        },
        Case {
            kind: "unknown heap policy",
            edit: ("duration_s = 300.0", "duration_s = 300.0\nheap = \"huge\""),
            expect: Parse("huge", "unknown variant"),
        },
        Case {
            kind: "negative duration",
            edit: ("duration_s = 300.0", "duration_s = -5.0"),
            expect: Invalid("run.duration_s", "must be a finite number > 0"),
        },
        Case {
            kind: "CI budget too small for one feature",
            edit: (LINK_1_3, "[[link]]\na = 1\nb = 3\nbyte_budget = 16\n"),
            expect: Invalid("link[0].byte_budget", "cannot carry even one feature"),
        },
        Case {
            kind: "unknown field (typo)",
            edit: ("duration_s = 300.0", "duraton_s = 300.0"),
            expect: Parse("duraton_s", "unknown field"),
        },
        Case {
            kind: "NaN",
            edit: ("record_interval_s = 1.0", "record_interval_s = nan"),
            expect: Invalid("run.record_interval_s", "must be > 0, got NaN"),
        },
        Case {
            kind: "self-link",
            edit: (LINK_1_3, "[[link]]\na = 3\nb = 3\n"),
            expect: Invalid("link[0]", "self-link"),
        },
        Case {
            kind: "disconnected tree",
            edit: (
                "[[link]]\na = 3\nb = 4\ntransport = \"shm\"\n",
                "# uav4 left without a link\n",
            ),
            expect: Invalid("link", "node(s) 4 not reachable"),
        },
        Case {
            kind: "loss probability above 1",
            edit: (
                LINK_1_3,
                "[[link]]\na = 1\nb = 3\nfaults = { loss = 1.5 }\n",
            ),
            expect: Invalid("link[0].faults.loss", "a probability must be in [0, 1]"),
        },
        Case {
            kind: "outage after the run",
            edit: (
                LINK_1_3,
                "[[link]]\na = 1\nb = 3\nfaults = { outages = [[400.0, 500.0]] }\n",
            ),
            expect: Invalid("link[0].faults.outages[0]", "after the run ends"),
        },
        Case {
            kind: "hub loss without a hub",
            edit: (
                "[fusion]",
                "[[event]]\nkind = \"hub_loss\"\nat_s = 10.0\n\n[fusion]",
            ),
            expect: Invalid("event[0].kind", "hub_loss needs fusion.mode"),
        },
        Case {
            kind: "listen on a shm link",
            edit: (
                LINK_1_3,
                "[[link]]\na = 1\nb = 3\nlisten = \"tcp/127.0.0.1:7447\"\n",
            ),
            expect: Invalid("link[0].listen", "only `net` links"),
        },
        Case {
            kind: "radio capacity zero",
            edit: (
                LINK_1_3,
                "[[link]]\na = 1\nb = 3\nradio = { bytes_per_s = 0.0 }\n",
            ),
            expect: Invalid("link[0].radio.bytes_per_s", "must be a finite number > 0"),
        },
        Case {
            kind: "radio capacity below one feature's submap per round",
            edit: (
                LINK_1_3,
                "[[link]]\na = 1\nb = 3\nradio = { bytes_per_s = 500.0 }\n",
            ),
            expect: Invalid(
                "link[0].radio.bytes_per_s",
                "less than one feature's submap",
            ),
        },
        Case {
            kind: "radio negative latency",
            edit: (
                LINK_1_3,
                "[[link]]\na = 1\nb = 3\nradio = { bytes_per_s = 32000.0, latency_s = -0.1 }\n",
            ),
            expect: Invalid("link[0].radio.latency_s", "must be a finite number ≥ 0"),
        },
        Case {
            kind: "radio zero range",
            edit: (
                LINK_1_3,
                "[[link]]\na = 1\nb = 3\nradio = { bytes_per_s = 32000.0, range_m = 0.0 }\n",
            ),
            expect: Invalid("link[0].radio.range_m", "must be a finite number > 0"),
        },
        Case {
            kind: "radio edge loss above 1",
            edit: (
                LINK_1_3,
                "[[link]]\na = 1\nb = 3\nradio = { bytes_per_s = 32000.0, range_m = 900.0, edge_loss = 1.5 }\n",
            ),
            expect: Invalid("link[0].radio.edge_loss", "must be in [0, 1]"),
        },
        Case {
            kind: "radio edge fraction without a range",
            edit: (
                LINK_1_3,
                "[[link]]\na = 1\nb = 3\nradio = { bytes_per_s = 32000.0, edge_fraction = 0.3 }\n",
            ),
            expect: Invalid(
                "link[0].radio.edge_fraction",
                "only applies to a radio with range_m",
            ),
        },
        Case {
            kind: "radio and a bandwidth cap",
            edit: (
                LINK_1_3,
                "[[link]]\na = 1\nb = 3\nradio = { bytes_per_s = 32000.0 }\nfaults = { bandwidth_bytes_per_s = 16000.0 }\n",
            ),
            expect: Invalid(
                "link[0].faults.bandwidth_bytes_per_s",
                "a radio link has its capacity",
            ),
        },
        Case {
            kind: "radio and a fixed byte budget",
            edit: (
                LINK_1_3,
                "[[link]]\na = 1\nb = 3\nradio = { bytes_per_s = 32000.0 }\nbyte_budget = 4096\n",
            ),
            expect: Invalid("link[0].byte_budget", "derives its per-round budget"),
        },
        Case {
            kind: "radio field typo",
            edit: (
                LINK_1_3,
                "[[link]]\na = 1\nb = 3\nradio = { bytes_per_s = 32000.0, rnage_m = 900.0 }\n",
            ),
            expect: Parse("rnage_m", "unknown field"),
        },
        Case {
            kind: "wrong type",
            edit: ("seed = 1\n", "seed = \"one\"\n"),
            expect: Parse("seed", "invalid type"),
        },
    ]
}

/// Writes every broken variant of tree-4 into `dir`: (case, file).
fn broken_files(dir: &Path) -> Vec<(Case, PathBuf)> {
    let base = std::fs::read_to_string(root().join("topologies/tree-4.toml")).expect("tree-4");
    cases()
        .into_iter()
        .enumerate()
        .map(|(i, c)| {
            assert!(
                base.contains(c.edit.0),
                "case `{}`: tree-4.toml no longer contains {:?}",
                c.kind,
                c.edit.0
            );
            let text = base.replacen(c.edit.0, c.edit.1, 1);
            let file = dir.join(format!("bad-{i:02}.toml"));
            std::fs::write(&file, text).expect("write");
            (c, file)
        })
        .collect()
}

/// The library: `Scenario::load` wraps the error in `ScenarioError::File` naming the file, and
/// the inner error is the expected `Invalid { field, reason }` or schema `Parse` error.
#[test]
fn bad_configs_are_rejected_by_the_library_with_file_field_and_reason() {
    let dir = tempfile::tempdir().expect("temp dir");
    let files = broken_files(dir.path());
    assert!(files.len() >= 10, "at least ten kinds of bad configuration");
    for (c, file) in &files {
        let err = Scenario::load(file).expect_err(c.kind);
        let ScenarioError::File { path, error } = &err else {
            panic!("{}: not wrapped with the file: {err:?}", c.kind)
        };
        assert_eq!(path, file, "{}", c.kind);
        let shown = err.to_string();
        assert!(
            shown.contains(&file.display().to_string()),
            "{}: {shown}",
            c.kind
        );
        match (&c.expect, error.as_ref()) {
            (
                Expect::Invalid(field, reason),
                ScenarioError::Invalid {
                    field: f,
                    reason: r,
                },
            ) => {
                assert_eq!(f, field, "{}: field", c.kind);
                assert!(r.contains(reason), "{}: reason {r:?}", c.kind);
            }
            (Expect::Parse(field, reason), ScenarioError::Parse(e)) => {
                let m = e.to_string();
                assert!(m.contains(field), "{}: {m}", c.kind);
                assert!(m.contains(reason), "{}: {m}", c.kind);
            }
            (_, other) => panic!("{}: unexpected error kind {other:?}", c.kind),
        }
        // The same text through `from_toml_str` gives the same inner error, without a file.
        let text = std::fs::read_to_string(file).expect("read back");
        let inner = Scenario::from_toml_str(&text).expect_err(c.kind);
        assert_eq!(inner.to_string(), error.to_string(), "{}", c.kind);
    }
}

/// The binary: `canopy check` on each broken file exits non-zero and its stderr names the file,
/// the field and the reason.
#[test]
fn bad_configs_fail_canopy_check_naming_file_field_and_reason() {
    let dir = tempfile::tempdir().expect("temp dir");
    for (c, file) in broken_files(dir.path()) {
        let (ok, stdout, stderr) = check(&file);
        assert!(!ok, "{}: canopy check accepted it:\n{stdout}", c.kind);
        let (field, reason) = match c.expect {
            Expect::Invalid(f, r) | Expect::Parse(f, r) => (f, r),
        };
        for needle in [file.display().to_string().as_str(), field, reason] {
            assert!(
                stderr.contains(needle),
                "{}: stderr does not name {needle:?}:\n{stderr}",
                c.kind
            );
        }
        assert!(
            !stderr.contains("panicked"),
            "{}: canopy panicked:\n{stderr}",
            c.kind
        );
    }
}
