//! The deployment part of a scenario: `[zenoh]` and `[[host]]` — a team spread over several
//! machines, each running its share (`canopy run SCENARIO --host NAME`), one of them the monitor
//! (`--monitor`), and how their zenoh sessions find each other.
//!
//! # Example
//! ```toml
//! [zenoh]
//! mode = "peer"                       # or "client": every session connects to `connect`
//! monitor = "tcp/10.0.0.1:7450"       # peer mode: the monitor listens here, hosts connect
//!
//! [[host]]
//! name = "alpha"
//! address = "10.0.0.1"                # the net links whose end `a` runs here listen on it
//! vehicles = [1, 2]
//!
//! [[host]]
//! name = "beta"
//! address = "10.0.0.2"
//! vehicles = [3, 4]
//! ```
//!
//! `[zenoh.tls]` (TLS on every zenoh link, a certificate per node) and `[secrets]`
//! `zenoh_password` (per-node users, access control at every listening session) apply to
//! single- and multi-host runs alike (docs/arch/deploy.md).
//!
//! Without `[[host]]` tables (or without `--host` / `--monitor`) a run is the single-host run.
//! With them, every vehicle (and the hub in central mode) belongs to exactly one host; `shm`
//! links stay within a host; a `net` link without `listen` listens on
//! `tcp/<address of a's host>:<port_base + link index>` so every host derives the same endpoint.

use std::collections::{BTreeMap, BTreeSet};

use serde::{Deserialize, Serialize};

use crate::network::{FusionMode, TransportKind, effective_links, node_names};
use crate::scenario::{Scenario, ScenarioError};

/// How the zenoh sessions of a multi-host run connect.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ZenohModeConfig {
    /// Peer to peer with explicit endpoints: net links between the vehicles' sessions, the host
    /// launchers connect to the monitor (default).
    #[default]
    Peer,
    /// Through a zenoh router (`canopy router`): every session of a multi-host run is a client
    /// of the router at `[zenoh].connect`, which routes between them and enforces the access
    /// control.
    Client,
}

/// `[zenoh]`: the zenoh side of a multi-host run.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ZenohDeploy {
    /// `peer` (default) or `client`.
    pub mode: ZenohModeConfig,
    /// `client` mode: the endpoint(s) of the zenoh router (`canopy router SCENARIO`, which
    /// enforces the run's access control and reports its refusals to the monitor); every
    /// session of a multi-host run — vehicles' `net` links, hub, host launchers, monitor —
    /// connects there and listens nowhere (*required* there). Several endpoints are several
    /// addresses of that router (a client uses the first that answers); the router listens on
    /// all of them unless told otherwise (`canopy router --listen`).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub connect: Vec<String>,
    /// `peer` mode: the endpoint the monitor listens on, e.g. `tcp/10.0.0.1:7450`; every host
    /// launcher connects to it (*required* in peer mode with `[[host]]`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub monitor: Option<String>,
    /// Key prefix of the run (default `canopy/<scenario name>`): every host of a run uses the same.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub key_prefix: Option<String>,
    /// zenoh multicast scouting (default false: sessions talk only to configured endpoints).
    pub multicast_scouting: bool,
    /// `[zenoh.tls]`: TLS on every zenoh link of the run (absent: plain TCP).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub tls: Option<TlsDeploy>,
}

/// `[zenoh.tls]`: every zenoh session of the run (the vehicles', the hub's, the host
/// launchers' and the monitor's) uses TLS (`tls/` endpoints), mutually authenticated against
/// the team's CA: each node presents its own certificate and private key, found by replacing
/// `{user}` in the file names by its zenoh user (the node's name, `host-NAME`, `monitor`).
/// Relative file names are relative to the scenario file; each file must exist on the host
/// whose process uses it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TlsDeploy {
    /// PEM certificate of the team's CA (*required*).
    pub root_ca: std::path::PathBuf,
    /// PEM certificate of each node, e.g. `certs/{user}.pem` (*required*; signed by the CA, its
    /// subject alternative names listing the addresses the node listens on).
    pub certificate: String,
    /// PEM (PKCS#8) private key of each node, e.g. `certs/{user}.key` (*required*).
    pub private_key: String,
}

/// The placeholder of [`TlsDeploy`] file names.
pub const TLS_USER: &str = "{user}";

impl TlsDeploy {
    /// The TLS files of `user`.
    pub fn for_user(&self, user: &str) -> canopy_transport::net::ZenohTls {
        canopy_transport::net::ZenohTls {
            root_ca: self.root_ca.clone(),
            certificate: self.certificate.replace(TLS_USER, user).into(),
            private_key: self.private_key.replace(TLS_USER, user).into(),
        }
    }

    /// Makes relative file names relative to `base` (the scenario's directory).
    pub fn resolve(&mut self, base: &std::path::Path) {
        if self.root_ca.is_relative() {
            self.root_ca = base.join(&self.root_ca);
        }
        for f in [&mut self.certificate, &mut self.private_key] {
            if std::path::Path::new(f.as_str()).is_relative() {
                *f = base.join(f.as_str()).to_string_lossy().into_owned();
            }
        }
    }
}

/// The zenoh endpoint protocol of the run: `tls` with `[zenoh.tls]`, else `tcp`.
pub fn endpoint_protocol(s: &Scenario) -> &'static str {
    if s.zenoh.tls.is_some() { "tls" } else { "tcp" }
}

impl ZenohDeploy {
    fn is_default(&self) -> bool {
        *self == Self::default()
    }
}

/// `skip_serializing_if` helper for [`Scenario::zenoh`].
pub(crate) fn zenoh_is_default(z: &ZenohDeploy) -> bool {
    z.is_default()
}

fn default_port_base() -> u16 {
    7460
}

/// `[[host]]`: one machine of a multi-host run and the nodes it runs.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HostSpec {
    /// Name, used on the command line (`--host NAME`) and as its zenoh user `host-NAME`
    /// (letters, digits, `_`, `-`) (*required*).
    pub name: String,
    /// Ids of the vehicles it runs.
    #[serde(default)]
    pub vehicles: Vec<u32>,
    /// It runs the hub (central mode).
    #[serde(default)]
    pub hub: bool,
    /// Where the other hosts reach it (IP address or host name): its net links listen there.
    /// *Required* when it holds the listening end (`a`) of a net link without `listen`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub address: Option<String>,
    /// Its net links without `listen` listen on port `port_base + link index` (default 7460).
    #[serde(default = "default_port_base")]
    pub port_base: u16,
}

/// zenoh user of the monitor.
pub const MONITOR_USER: &str = "monitor";

/// zenoh user of the router (`canopy router`, client mode); reserved (no node, host or the
/// monitor may take it).
pub const ROUTER_USER: &str = "router";

/// The run's sessions are clients of zenoh router(s) (`[zenoh].mode = "client"`) — in a
/// multi-host run (`--host`, `--monitor`, `canopy router`); a single-host `canopy run` keeps its
/// vehicles' net links peer to peer on loopback.
pub fn client_mode(s: &Scenario) -> bool {
    s.zenoh.mode == ZenohModeConfig::Client && !s.hosts.is_empty()
}

/// Every zenoh user of a multi-host run: its fusion nodes (vehicles, the hub), its host
/// launchers (`host-NAME`) and the monitor.
pub fn team_users(s: &Scenario) -> Vec<String> {
    let mut users: Vec<String> = node_names(s).into_values().collect();
    users.extend(s.hosts.iter().map(host_user));
    users.push(MONITOR_USER.to_string());
    users
}

/// The access control of a client-mode run's router (`canopy router`), built from the key
/// layout, default deny:
/// - fusion plane (`key_prefix`): both directions of every `net` link — the user of each end
///   may publish, subscribe and hold / watch liveliness only on its own side of that link, so
///   two nodes talk through the router exactly on their `net` links (not on `shm` ones, not
///   with a non-neighbour, not as another node);
/// - control plane (`control_prefix`): host `i` ↔ the monitor for every host, and the router
///   ↔ the monitor (its own link, [`crate::process::protocol::ROUTER_ID`], on which it reports
///   its refusals).
pub fn router_access(s: &Scenario) -> canopy_transport::access::ZenohAccess {
    use crate::process::protocol::{MONITOR_ID, ROUTER_ID};
    use canopy_transport::access::{AclLink, ZenohAccess};
    let names = node_names(s);
    let user = |id: u32| {
        names
            .get(&id)
            .cloned()
            .unwrap_or_else(|| format!("node{id}"))
    };
    let both = |ua: String, a: u32, ub: String, b: u32| {
        [
            AclLink {
                user: ua,
                from: a,
                to: b,
            },
            AclLink {
                user: ub,
                from: b,
                to: a,
            },
        ]
    };
    let fusion: Vec<AclLink> = effective_links(s)
        .iter()
        .filter(|l| l.transport == TransportKind::Net)
        .flat_map(|l| both(user(l.a), l.a, user(l.b), l.b))
        .collect();
    let mut control: Vec<AclLink> = s
        .hosts
        .iter()
        .enumerate()
        .flat_map(|(i, h)| both(host_user(h), i as u32, MONITOR_USER.into(), MONITOR_ID))
        .collect();
    // The router's own link: only the monitor's side is a client's (the router's own session
    // is not subject to its access control; its egress to the monitor is).
    control.push(AclLink {
        user: MONITOR_USER.into(),
        from: MONITOR_ID,
        to: ROUTER_ID,
    });
    ZenohAccess::for_links(&key_prefix(s), &fusion)
        .merge(ZenohAccess::for_links(&control_prefix(s), &control))
}

/// zenoh user of a host launcher.
pub fn host_user(h: &HostSpec) -> String {
    format!("host-{}", h.name)
}

/// The key prefix of a multi-host run (`[zenoh].key_prefix`, default `canopy/<name>`).
pub fn key_prefix(s: &Scenario) -> String {
    if let Some(p) = &s.zenoh.key_prefix {
        return p.clone();
    }
    let name = s.run.name.as_deref().unwrap_or("run");
    let mut out = String::from("canopy/");
    let mut dash = false;
    for c in name.chars() {
        if c.is_ascii_alphanumeric() || c == '_' || c == '-' {
            out.push(c);
            dash = false;
        } else if !dash {
            out.push('-');
            dash = true;
        }
    }
    while out.ends_with('-') || out.ends_with('/') {
        out.pop();
    }
    if out == "canopy" {
        out.push_str("/run");
    }
    out
}

/// The key prefix of the control plane (host launchers ↔ monitor) under the run's prefix.
pub fn control_prefix(s: &Scenario) -> String {
    format!("{}/ctl", key_prefix(s))
}

/// The host running node `node` (a vehicle, or the hub), with its index.
pub fn host_of(s: &Scenario, node: u32) -> Option<(usize, &HostSpec)> {
    let hub = s.fusion.mode == FusionMode::Central && node == s.fusion.hub_id;
    s.hosts
        .iter()
        .enumerate()
        .find(|(_, h)| h.vehicles.contains(&node) || (hub && h.hub))
}

/// The host called `name`, with its index.
pub fn host_named<'s>(s: &'s Scenario, name: &str) -> Option<(usize, &'s HostSpec)> {
    s.hosts.iter().enumerate().find(|(_, h)| h.name == name)
}

/// The fusion nodes a host runs: its vehicles (scenario order) and the hub if it has it.
pub fn local_nodes(s: &Scenario, h: &HostSpec) -> Vec<u32> {
    let mut v: Vec<u32> = s
        .vehicles
        .iter()
        .map(|v| v.id)
        .filter(|id| h.vehicles.contains(id))
        .collect();
    if h.hub && s.fusion.mode == FusionMode::Central {
        v.push(s.fusion.hub_id);
    }
    v
}

/// Fills the `listen` endpoint of every net link without one from the hosts: `tcp/<address of
/// the host of a>:<its port_base + link index>` (the same on every host).
pub fn resolve_endpoints(s: &mut Scenario) -> Result<(), ScenarioError> {
    let derived: Vec<(usize, String)> = effective_links(s)
        .iter()
        .enumerate()
        .filter(|(_, l)| l.transport == TransportKind::Net && l.listen.is_none())
        .map(|(i, l)| {
            let (_, h) = host_of(s, l.a).ok_or_else(|| {
                ScenarioError::invalid(format!("link[{i}]"), "its end a runs on no host")
            })?;
            let addr = h.address.as_deref().ok_or_else(|| {
                ScenarioError::invalid(
                    format!("host `{}`.address", h.name),
                    format!("needed: link[{i}] ({} - {}) listens on this host", l.a, l.b),
                )
            })?;
            let port = u32::from(h.port_base) + i as u32;
            let port = u16::try_from(port).map_err(|_| {
                ScenarioError::invalid(
                    format!("host `{}`.port_base", h.name),
                    format!("port_base + link index {i} exceeds 65535"),
                )
            })?;
            let host = if addr.contains(':') {
                format!("[{addr}]")
            } else {
                addr.to_string()
            };
            Ok((i, format!("{}/{host}:{port}", endpoint_protocol(s))))
        })
        .collect::<Result<_, ScenarioError>>()?;
    if s.links.is_empty() && !derived.is_empty() {
        // Central mode without [[link]]: the generated star becomes explicit.
        s.links = effective_links(s);
    }
    for (i, ep) in derived {
        s.links[i].listen = Some(ep);
    }
    Ok(())
}

fn valid_name(n: &str) -> bool {
    !n.is_empty()
        && n.bytes()
            .all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-')
}

/// Validates `[zenoh]` and `[[host]]` against the rest of the scenario.
pub fn validate(s: &Scenario) -> Result<(), ScenarioError> {
    let z = &s.zenoh;
    if let Some(p) = &z.key_prefix {
        let ok = valid_name(&p.replace('/', "_")) && !p.starts_with('/') && !p.ends_with('/');
        if !ok {
            return Err(ScenarioError::invalid(
                "zenoh.key_prefix",
                format!("{p:?}: letters, digits, `_`, `-` and inner `/` only"),
            ));
        }
    }
    for (i, ep) in z.connect.iter().chain(z.monitor.iter()).enumerate() {
        if !ep.contains('/') {
            return Err(ScenarioError::invalid(
                if i < z.connect.len() {
                    format!("zenoh.connect[{i}]")
                } else {
                    "zenoh.monitor".into()
                },
                format!("{ep:?} is not a zenoh endpoint (e.g. `tcp/10.0.0.1:7447`)"),
            ));
        }
    }
    let proto = format!("{}/", endpoint_protocol(s));
    let configured = z
        .connect
        .iter()
        .map(|e| ("zenoh.connect".to_string(), e))
        .chain(z.monitor.iter().map(|e| ("zenoh.monitor".to_string(), e)))
        .chain(
            s.links
                .iter()
                .enumerate()
                .filter(|(_, l)| l.transport == TransportKind::Net)
                .filter_map(|(i, l)| l.listen.as_ref().map(|e| (format!("link[{i}].listen"), e))),
        )
        .collect::<Vec<_>>();
    if let Some((field, ep)) = configured.iter().find(|(_, e)| !e.starts_with(&proto)) {
        return Err(ScenarioError::invalid(
            field.clone(),
            format!(
                "{ep:?}: this run's zenoh endpoints are {proto}… ({})",
                if z.tls.is_some() {
                    "[zenoh.tls] is set"
                } else {
                    "no [zenoh.tls]"
                }
            ),
        ));
    }
    if let Some(t) = &z.tls {
        for (field, f) in [
            ("certificate", &t.certificate),
            ("private_key", &t.private_key),
        ] {
            if !f.contains(TLS_USER) {
                return Err(ScenarioError::invalid(
                    format!("zenoh.tls.{field}"),
                    format!("{f:?} must contain {TLS_USER} (each node has its own)"),
                ));
            }
        }
    }
    if s.hosts.is_empty() {
        return Ok(());
    }
    match z.mode {
        ZenohModeConfig::Peer if z.monitor.is_none() => {
            return Err(ScenarioError::invalid(
                "zenoh.monitor",
                "peer mode with [[host]] tables needs the monitor's endpoint \
                 (e.g. `tcp/10.0.0.1:7450`)",
            ));
        }
        ZenohModeConfig::Client if z.connect.is_empty() => {
            return Err(ScenarioError::invalid(
                "zenoh.connect",
                "client mode needs the zenoh router endpoint(s)",
            ));
        }
        ZenohModeConfig::Client if z.monitor.is_some() => {
            return Err(ScenarioError::invalid(
                "zenoh.monitor",
                "client mode reaches the monitor through the router(s) of [zenoh].connect: \
                 remove `monitor` (it is the endpoint the monitor listens on in peer mode)",
            ));
        }
        _ => {}
    }
    let names = node_names(s);
    let mut users: BTreeMap<String, String> = names
        .iter()
        .map(|(id, n)| (n.clone(), format!("node {id}")))
        .collect();
    for (reserved, what) in [(MONITOR_USER, "the monitor"), (ROUTER_USER, "the router")] {
        if let Some(node) = users.insert(reserved.into(), what.into()) {
            return Err(ScenarioError::invalid(
                "vehicle.name",
                format!("`{reserved}` is the zenoh user of {what}; {node} may not be called so"),
            ));
        }
    }
    let mut seen: BTreeMap<u32, String> = BTreeMap::new();
    let mut hub_hosts = 0;
    for (i, h) in s.hosts.iter().enumerate() {
        let field = format!("host[{i}]");
        if !valid_name(&h.name) {
            return Err(ScenarioError::invalid(
                format!("{field}.name"),
                format!("{:?}: letters, digits, `_` and `-` only", h.name),
            ));
        }
        if let Some(other) = users.insert(host_user(h), format!("host[{i}]")) {
            return Err(ScenarioError::invalid(
                format!("{field}.name"),
                format!("its zenoh user `{}` is also {other}", host_user(h)),
            ));
        }
        for &v in &h.vehicles {
            if !s.vehicles.iter().any(|x| x.id == v) {
                return Err(ScenarioError::invalid(
                    format!("{field}.vehicles"),
                    format!("no vehicle with id {v}"),
                ));
            }
            if let Some(other) = seen.insert(v, h.name.clone()) {
                return Err(ScenarioError::invalid(
                    format!("{field}.vehicles"),
                    format!("vehicle {v} already runs on host `{other}`"),
                ));
            }
        }
        if h.hub {
            if s.fusion.mode != FusionMode::Central {
                return Err(ScenarioError::invalid(
                    format!("{field}.hub"),
                    "only central mode has a hub",
                ));
            }
            hub_hosts += 1;
        }
    }
    if let Some(v) = s.vehicles.iter().find(|v| !seen.contains_key(&v.id)) {
        return Err(ScenarioError::invalid(
            "host",
            format!("vehicle {} runs on no host", v.display_name()),
        ));
    }
    if s.fusion.mode == FusionMode::Central && hub_hosts != 1 {
        return Err(ScenarioError::invalid(
            "host",
            format!("exactly one host must run the hub (`hub = true`), found {hub_hosts}"),
        ));
    }
    let hosts: BTreeSet<&str> = s.hosts.iter().map(|h| h.name.as_str()).collect();
    if hosts.len() != s.hosts.len() {
        return Err(ScenarioError::invalid("host", "host names must be unique"));
    }
    for (i, l) in effective_links(s).iter().enumerate() {
        let (ha, hb) = (host_of(s, l.a), host_of(s, l.b));
        if let (Some((ia, a)), Some((ib, b))) = (ha, hb)
            && ia != ib
            && l.transport == TransportKind::Shm
        {
            return Err(ScenarioError::invalid(
                format!("link[{i}].transport"),
                format!(
                    "shm (shared memory) cannot join hosts `{}` and `{}`: use transport = \"net\"",
                    a.name, b.name
                ),
            ));
        }
    }
    // The derived endpoints exist (addresses, ports).
    if z.mode == ZenohModeConfig::Peer {
        let mut copy = s.clone();
        resolve_endpoints(&mut copy)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tree8_on_three_hosts() -> Scenario {
        let text = std::fs::read_to_string(
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../topologies/tree-8.toml"),
        )
        .unwrap();
        let mut s: Scenario = toml::from_str(&text).unwrap();
        s.zenoh.monitor = Some("tcp/10.0.0.1:7450".into());
        for (name, addr, vehicles) in [
            ("alpha", "10.0.0.1", vec![1, 2]),
            ("beta", "10.0.0.2", vec![3, 4, 7]),
            ("gamma", "10.0.0.3", vec![5, 6, 8]),
        ] {
            s.hosts.push(HostSpec {
                name: name.into(),
                vehicles,
                hub: false,
                address: Some(addr.into()),
                port_base: 7460,
            });
        }
        s.links[1].listen = None;
        s
    }

    /// The shipped example: the endpoints its comments announce, links inside a host on shm.
    #[test]
    fn the_two_hosts_example_derives_the_endpoints_it_documents() {
        let mut s = Scenario::load(
            &std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../topologies/two-hosts.toml"),
        )
        .unwrap();
        resolve_endpoints(&mut s).unwrap();
        let listen: Vec<Option<&str>> = s.links.iter().map(|l| l.listen.as_deref()).collect();
        assert_eq!(
            listen,
            vec![None, Some("tcp/10.0.0.2:7461"), Some("tcp/10.0.0.1:7462")]
        );
        assert_eq!(key_prefix(&s), "canopy/two-hosts");
        let alpha = host_named(&s, "alpha").unwrap().1;
        assert_eq!(local_nodes(&s, alpha), vec![1, 3]);
    }

    #[test]
    fn endpoints_are_derived_from_the_host_of_the_listening_end() {
        let mut s = tree8_on_three_hosts();
        validate(&s).unwrap();
        resolve_endpoints(&mut s).unwrap();
        // link[1] is uav2 (alpha) – uav3; link[3] uav2 – uav6; link[6] uav7 (beta) – uav8.
        assert_eq!(s.links[1].listen.as_deref(), Some("tcp/10.0.0.1:7461"));
        assert_eq!(s.links[3].listen.as_deref(), Some("tcp/10.0.0.1:7463"));
        assert_eq!(s.links[6].listen.as_deref(), Some("tcp/10.0.0.2:7466"));
        assert_eq!(key_prefix(&s), "canopy/tree-8");
    }

    #[test]
    fn a_bad_deployment_names_the_field() {
        let mut s = tree8_on_three_hosts();
        s.hosts[2].vehicles.push(3);
        let e = validate(&s).unwrap_err().to_string();
        assert!(
            e.contains("host[2].vehicles") && e.contains("already runs"),
            "{e}"
        );

        let mut s = tree8_on_three_hosts();
        s.hosts[1].vehicles.retain(|&v| v != 4);
        s.hosts[2].vehicles.push(4);
        // uav3 (beta) – uav4 (now gamma) is an shm link.
        let e = validate(&s).unwrap_err().to_string();
        assert!(e.contains("link[2].transport") && e.contains("shm"), "{e}");

        let mut s = tree8_on_three_hosts();
        s.hosts[2].vehicles.pop();
        let e = validate(&s).unwrap_err().to_string();
        assert!(e.contains("uav8 runs on no host"), "{e}");

        let mut s = tree8_on_three_hosts();
        s.hosts[0].address = None;
        let e = validate(&s).unwrap_err().to_string();
        assert!(e.contains("host `alpha`.address"), "{e}");

        let mut s = tree8_on_three_hosts();
        s.zenoh.monitor = None;
        let e = validate(&s).unwrap_err().to_string();
        assert!(e.contains("zenoh.monitor"), "{e}");
    }

    fn tls(certificate: &str) -> TlsDeploy {
        TlsDeploy {
            root_ca: "certs/ca.pem".into(),
            certificate: certificate.into(),
            private_key: "certs/{user}.key".into(),
        }
    }

    /// With `[zenoh.tls]` the derived endpoints are TLS ones and each user gets its own files.
    #[test]
    fn tls_derives_tls_endpoints_and_per_user_files() {
        let mut s = tree8_on_three_hosts();
        s.zenoh.tls = Some(tls("certs/{user}.pem"));
        s.zenoh.monitor = Some("tls/10.0.0.1:7450".into());
        validate(&s).unwrap();
        resolve_endpoints(&mut s).unwrap();
        assert_eq!(s.links[1].listen.as_deref(), Some("tls/10.0.0.1:7461"));
        let f = s.zenoh.tls.as_ref().unwrap().for_user("host-beta");
        assert_eq!(
            f.certificate,
            std::path::PathBuf::from("certs/host-beta.pem")
        );
        assert_eq!(
            f.private_key,
            std::path::PathBuf::from("certs/host-beta.key")
        );
        assert_eq!(f.root_ca, std::path::PathBuf::from("certs/ca.pem"));
    }

    /// Each bad `[zenoh]` / `[[host]]` table is refused with the field and the reason.
    #[test]
    fn bad_host_tables_are_refused_with_field_and_reason() {
        type Spoil = Box<dyn Fn(&mut Scenario)>;
        let cases: Vec<(&str, Spoil, &[&str])> = vec![
            (
                "unknown vehicle",
                Box::new(|s| s.hosts[0].vehicles.push(42)),
                &["host[0].vehicles", "no vehicle with id 42"],
            ),
            (
                "bad host name",
                Box::new(|s| s.hosts[1].name = "be ta".into()),
                &["host[1].name", "letters, digits"],
            ),
            (
                "duplicate host name",
                Box::new(|s| s.hosts[2].name = "alpha".into()),
                &["host[2].name", "host-alpha", "host[0]"],
            ),
            (
                "hub outside central mode",
                Box::new(|s| s.hosts[0].hub = true),
                &["host[0].hub", "only central mode"],
            ),
            (
                "client mode without routers",
                Box::new(|s| s.zenoh.mode = ZenohModeConfig::Client),
                &["zenoh.connect", "router"],
            ),
            (
                "not an endpoint",
                Box::new(|s| s.zenoh.monitor = Some("10.0.0.1:7450".into())),
                &["zenoh.monitor", "not a zenoh endpoint"],
            ),
            (
                "port overflow",
                Box::new(|s| s.hosts[0].port_base = 65_535),
                &["host `alpha`.port_base", "exceeds 65535"],
            ),
            (
                "bad key prefix",
                Box::new(|s| s.zenoh.key_prefix = Some("/canopy/x".into())),
                &["zenoh.key_prefix"],
            ),
            (
                "plain TCP endpoint under TLS",
                Box::new(|s| s.zenoh.tls = Some(tls("certs/{user}.pem"))),
                &["zenoh.monitor", "tls/", "[zenoh.tls] is set"],
            ),
            (
                "one certificate for every node",
                Box::new(|s| {
                    s.zenoh.tls = Some(tls("certs/node.pem"));
                    s.zenoh.monitor = Some("tls/10.0.0.1:7450".into());
                }),
                &["zenoh.tls.certificate", "{user}"],
            ),
            (
                "TLS endpoint without TLS",
                Box::new(|s| s.zenoh.monitor = Some("tls/10.0.0.1:7450".into())),
                &["zenoh.monitor", "tcp/", "no [zenoh.tls]"],
            ),
        ];
        for (what, spoil, expected) in cases {
            let mut s = tree8_on_three_hosts();
            spoil(&mut s);
            let e = validate(&s)
                .err()
                .unwrap_or_else(|| panic!("{what}: accepted"))
                .to_string();
            for x in expected {
                assert!(e.contains(x), "{what}: {e:?} lacks {x:?}");
            }
        }
    }

    /// Client mode: the router's access control grants each node exactly its own side of its
    /// `net` links (none of its `shm` ones), each host launcher its control link, the monitor
    /// its side of every control link and of the router's; every user of the run is listed.
    #[test]
    fn the_router_grants_exactly_the_net_links_and_the_control_links() {
        use crate::process::protocol::{MONITOR_ID, ROUTER_ID};
        use canopy_transport::access::{AclFlow, AclMessage};
        let mut s = tree8_on_three_hosts();
        s.zenoh.mode = ZenohModeConfig::Client;
        s.zenoh.monitor = None;
        s.zenoh.connect = vec!["tcp/10.0.0.9:7447".into()];
        validate(&s).unwrap();
        assert!(client_mode(&s));
        let acl = router_access(&s);
        let puts = |user: &str| -> Vec<String> {
            let mut v: Vec<String> = acl
                .grants
                .iter()
                .filter(|g| {
                    g.user == user && g.flow == AclFlow::Ingress && g.message == AclMessage::Put
                })
                .flat_map(|g| g.keys.clone())
                .collect();
            v.sort();
            v
        };
        // uav2: net links to uav3 and uav6; its shm link to uav1 is not the router's business.
        assert_eq!(
            puts("uav2"),
            vec!["canopy/tree-8/link/2/3", "canopy/tree-8/link/2/6"]
        );
        assert_eq!(puts("uav1"), Vec::<String>::new());
        assert_eq!(puts("uav8"), vec!["canopy/tree-8/link/8/7"]);
        assert_eq!(
            puts("host-beta"),
            vec![format!("canopy/tree-8/ctl/link/1/{MONITOR_ID}")]
        );
        let mut monitor = puts("monitor");
        monitor.retain(|k| k.ends_with(&format!("/{ROUTER_ID}")));
        assert_eq!(
            monitor,
            vec![format!("canopy/tree-8/ctl/link/{MONITOR_ID}/{ROUTER_ID}")]
        );
        assert_eq!(
            acl.announce,
            vec!["canopy/tree-8/link/**", "canopy/tree-8/ctl/link/**"]
        );
        let users = team_users(&s);
        for u in ["uav1", "uav8", "host-alpha", "host-gamma", "monitor"] {
            assert!(users.iter().any(|x| x == u), "{u} in {users:?}");
        }
        assert!(!users.iter().any(|x| x == ROUTER_USER));

        // Client mode has no monitor endpoint; `router` is the router's user.
        let mut bad = s.clone();
        bad.zenoh.monitor = Some("tcp/10.0.0.1:7450".into());
        let e = validate(&bad).unwrap_err().to_string();
        assert!(
            e.contains("zenoh.monitor") && e.contains("client mode"),
            "{e}"
        );
        let mut bad = s.clone();
        bad.hosts[0].name = "x".into();
        bad.vehicles[0].name = Some(ROUTER_USER.into());
        let e = validate(&bad).unwrap_err().to_string();
        assert!(e.contains("router"), "{e}");
    }

    /// Central mode: the hub belongs to exactly one host and its links to vehicles elsewhere
    /// become net links listening on the hub's host.
    #[test]
    fn central_mode_needs_one_hub_host() {
        let text = std::fs::read_to_string(
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../topologies/central-4.toml"),
        )
        .unwrap();
        let mut s: Scenario = toml::from_str(&text).unwrap();
        // The generated star (central-4 spells it out as shm links).
        s.links.clear();
        s.zenoh.monitor = Some("tcp/10.0.0.1:7450".into());
        let ids: Vec<u32> = s.vehicles.iter().map(|v| v.id).collect();
        let (first, rest) = ids.split_at(2);
        for (name, addr, vehicles, hub) in [
            ("alpha", "10.0.0.1", first.to_vec(), false),
            ("beta", "10.0.0.2", rest.to_vec(), false),
        ] {
            s.hosts.push(HostSpec {
                name: name.into(),
                vehicles,
                hub,
                address: Some(addr.into()),
                port_base: 7460,
            });
        }
        let e = validate(&s).unwrap_err().to_string();
        assert!(e.contains("exactly one host must run the hub"), "{e}");
        s.hosts[0].hub = true;
        validate(&s).unwrap();
        resolve_endpoints(&mut s).unwrap();
        for (i, l) in s.links.iter().enumerate() {
            let remote = rest.contains(&l.b);
            assert_eq!(
                l.transport == TransportKind::Net,
                remote,
                "link[{i}] {l:?}: net exactly when the vehicle is on another host than the hub"
            );
            if remote {
                assert_eq!(l.listen, Some(format!("tcp/10.0.0.1:{}", 7460 + i)));
            }
        }
    }
}
