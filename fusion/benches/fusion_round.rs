//! One DDF fusion round per link, marginal → information → delta, at 100 and 300 features,
//! side by side with a raw faer Cholesky inverse of the same size (the floor: Y = P_mm⁻¹ is
//! the dominant cost). Prints the time ratio and the bytes per round per link, dense f64 and
//! block-sparse. The EKF fuse-back joins at integration.
//!
//! The data: a map information with direct observations of every feature and relative
//! observations between random pairs (sparse coupling), the channel synchronised on it, then
//! one round's new observations of 10 features (coupled among themselves) before the marginal
//! P_mm = Y⁻¹ is handed to the round.
//!
//! Run: `cargo bench -p canopy-fusion --bench fusion_round`.

use canopy_fusion::ddf::{Body, DdfConfig, DdfNode, FuseTarget, MapSource, Outgoing};
use canopy_fusion::info::{InfoError, MapInformation, MapMarginal};
use canopy_fusion::sensor::FeatureId;
use canopy_fusion::topology::NodeId;
use criterion::{BatchSize, Criterion};
use faer::linalg::solvers::DenseSolveCore;
use faer::{Col, Mat, Side};
use nalgebra::{Matrix3, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::hint::black_box;
use std::time::Instant;

const A: NodeId = NodeId(1);
const B: NodeId = NodeId(2);

fn origin() -> Vector3<f64> {
    Vector3::new(-2.7e6, 4.3e6, 3.9e6)
}

/// Adds a 3 × 3 block s·I·w to (i, j).
fn add_block(m: &mut Mat<f64>, i: usize, j: usize, w: f64) {
    for a in 0..3 {
        m[(3 * i + a, 3 * j + a)] += w;
    }
}

/// Information of direct observations of every feature and ~2n relative observations.
fn base_information(n: usize, rng: &mut ChaCha8Rng) -> MapInformation {
    let mut y = Mat::zeros(3 * n, 3 * n);
    for i in 0..n {
        add_block(&mut y, i, i, rng.random_range(0.05..1.0));
    }
    for _ in 0..2 * n {
        let (i, j) = (rng.random_range(0..n), rng.random_range(0..n));
        if i != j {
            let w = rng.random_range(0.1..2.0);
            add_block(&mut y, i, i, w);
            add_block(&mut y, j, j, w);
            add_block(&mut y, i, j, -w);
            add_block(&mut y, j, i, -w);
        }
    }
    MapInformation {
        ids: (0..n as u64).collect(),
        origin: origin(),
        matrix: y,
        vector: Col::from_fn(3 * n, |_| rng.random_range(-100.0..100.0)),
    }
}

/// New observations of 10 features, relative among consecutive ones.
fn new_observations(n: usize, rng: &mut ChaCha8Rng) -> MapInformation {
    let mut d = MapInformation::zeros_over(&(0..n as u64).collect::<Vec<_>>(), origin()).unwrap();
    let picked: Vec<usize> = (0..10).map(|_| rng.random_range(0..n)).collect();
    for w in picked.windows(2) {
        let (i, j) = (w[0], w[1]);
        let s = rng.random_range(0.5..2.0);
        add_block(&mut d.matrix, i, i, s);
        if i != j {
            add_block(&mut d.matrix, j, j, s);
            add_block(&mut d.matrix, i, j, -s);
            add_block(&mut d.matrix, j, i, -s);
        }
        for a in 0..3 {
            d.vector[3 * i + a] += rng.random_range(-10.0..10.0);
        }
    }
    d
}

/// Two DDF nodes with a synchronised channel; A's channel has sent `base` already.
fn synced_node(base: &MapInformation) -> DdfNode {
    let cfg = DdfConfig::default();
    let mut a = DdfNode::new(A, 11, [B], origin(), cfg.clone());
    let mut b = DdfNode::new(B, 22, [A], origin(), cfg);
    let mut ya = base.clone();
    let mut yb = MapInformation::zero(origin());
    let mut queue: Vec<(NodeId, Outgoing)> = Vec::new();
    queue.extend(a.on_link_up(0.0, B).unwrap().into_iter().map(|o| (A, o)));
    queue.extend(b.on_link_up(0.0, A).unwrap().into_iter().map(|o| (B, o)));
    let mut pump = |queue: &mut Vec<(NodeId, Outgoing)>, a: &mut DdfNode, b: &mut DdfNode| {
        while let Some((from, o)) = queue.pop() {
            let (node, est): (&mut DdfNode, &mut dyn FuseTarget) = if o.to == A {
                (a, &mut ya)
            } else {
                (b, &mut yb)
            };
            let replies = node.on_message(0.0, from, o.message, est).unwrap();
            queue.extend(replies.into_iter().map(|r| (o.to, r)));
        }
    };
    pump(&mut queue, &mut a, &mut b);
    // A sends the base map once, so that the next round's delta is only what is new.
    let out = a.on_round(1.0, &mut base.clone()).unwrap();
    queue.extend(out.messages.into_iter().map(|o| (A, o)));
    pump(&mut queue, &mut a, &mut b);
    assert!(a.channel(B).unwrap().synced);
    a
}

struct Case {
    n: usize,
    marginal: MapMarginal,
    node: DdfNode,
}

fn case(n: usize) -> Case {
    let mut rng = ChaCha8Rng::seed_from_u64(n as u64);
    let base = base_information(n, &mut rng);
    let node = synced_node(&base);
    let now = base.add(&new_observations(n, &mut rng)).unwrap();
    let marginal = now.to_marginal().unwrap();
    Case { n, marginal, node }
}

/// Hands the node the information it was given, without copying it.
struct Given(Option<MapInformation>);

impl MapSource for Given {
    fn information(&mut self) -> Result<MapInformation, InfoError> {
        Ok(self.0.take().expect("read once per round"))
    }
    fn feature_covariances(&self) -> Vec<(FeatureId, Matrix3<f64>)> {
        Vec::new()
    }
    fn marginal(&self, _: &[FeatureId]) -> MapMarginal {
        unreachable!("exact links only")
    }
}

/// The round under test: Y = P⁻¹, y = Y(x − o) (21.86, 21.87), then the channel's delta.
fn fusion_round(c: &Case, node: &mut DdfNode) -> Vec<Outgoing> {
    let info = MapInformation::from_marginal(&c.marginal, origin()).unwrap();
    node.on_round(2.0, &mut Given(Some(info))).unwrap().messages
}

fn faer_inverse(p: &Mat<f64>) -> Mat<f64> {
    p.as_ref().llt(Side::Lower).unwrap().inverse()
}

fn median_seconds(mut f: impl FnMut(), reps: usize) -> f64 {
    let mut t: Vec<f64> = (0..reps)
        .map(|_| {
            let s = Instant::now();
            f();
            s.elapsed().as_secs_f64()
        })
        .collect();
    t.sort_by(f64::total_cmp);
    t[reps / 2]
}

fn main() {
    // The process set-up of every canopy process, for both sides of the comparison.
    canopy_fusion::runtime::tune_allocator();
    canopy_fusion::runtime::flush_subnormals_to_zero();
    let cases: Vec<Case> = [100, 300].into_iter().map(case).collect();
    let mut criterion = Criterion::default().configure_from_args().sample_size(20);
    for c in &cases {
        let mut group = criterion.benchmark_group(format!("fusion_round/{}", c.n));
        group.bench_function("ddf_round", |b| {
            b.iter_batched(
                || c.node.clone(),
                |mut node| black_box(fusion_round(c, &mut node)),
                BatchSize::LargeInput,
            )
        });
        group.bench_function("faer_cholesky_inverse", |b| {
            b.iter(|| black_box(faer_inverse(&c.marginal.covariance)))
        });
        group.finish();
    }
    criterion.final_summary();

    // Side-by-side summary (own interleaved medians, so that the ratio is printed).
    println!();
    println!(
        "{:>8} {:>6} {:>14} {:>16} {:>7} {:>14} {:>18} {:>12}",
        "features",
        "dim",
        "round [ms]",
        "chol+inv [ms]",
        "ratio",
        "dense [B]",
        "block-sparse [B]",
        "blocks sent"
    );
    for c in &cases {
        let reps = 15;
        let mut rounds = Vec::new();
        let mut invs = Vec::new();
        for _ in 0..reps {
            let mut node = c.node.clone();
            rounds.push(median_seconds(
                || drop(black_box(fusion_round(c, &mut node))),
                1,
            ));
            invs.push(median_seconds(
                || drop(black_box(faer_inverse(&c.marginal.covariance))),
                1,
            ));
        }
        rounds.sort_by(f64::total_cmp);
        invs.sort_by(f64::total_cmp);
        let (r, i) = (rounds[reps / 2], invs[reps / 2]);
        let mut node = c.node.clone();
        let out = fusion_round(c, &mut node);
        let delta = out
            .iter()
            .find_map(|o| match &o.message.body {
                Body::Delta { info, .. } => Some((o, info)),
                _ => None,
            })
            .expect("a delta this round");
        let sparse_bytes =
            bincode::serde::encode_to_vec(&delta.0.message, bincode::config::standard())
                .unwrap()
                .len();
        let full = MapInformation::from_marginal(&c.marginal, origin()).unwrap();
        let sparsity = delta.1.block_sparsity(0.0);
        println!(
            "{:>8} {:>6} {:>14.2} {:>16.2} {:>7.2} {:>14} {:>18} {:>12}",
            c.n,
            3 * c.n,
            r * 1e3,
            i * 1e3,
            r / i,
            full.dense_wire_bytes(),
            sparse_bytes,
            format!("{}/{}", sparsity.matrix_blocks.len(), c.n * (c.n + 1) / 2)
        );
    }
}
