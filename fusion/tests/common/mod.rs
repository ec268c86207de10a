//! A small deterministic network simulator for the DDF state machine, and linear-Gaussian
//! static-map data. Shared by the `ddf_*` integration tests (each uses a part of it).
#![allow(dead_code)]

use canopy_fusion::ci::{CiCriterion, Submap};
use canopy_fusion::ddf::{DdfConfig, DdfMessage, DdfNode, FuseRejected, FuseTarget, Mode};
use canopy_fusion::info::MapInformation;
use canopy_fusion::keys::{KeyMap, Merge};
use canopy_fusion::sensor::FeatureId;
use canopy_fusion::topology::{NodeId, Topology};
use faer::{Col, Mat};
use nalgebra::{Matrix3, Vector3};
use rand::seq::{IndexedRandom, SliceRandom};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::collections::BTreeMap;

/// The team origin used in the tests: ECEF-sized, to exercise the origin convention.
pub fn origin() -> Vector3<f64> {
    Vector3::new(-2.7e6, 4.3e6, 3.9e6)
}

/// Tree shapes of the property tests.
#[derive(Clone, Copy, Debug)]
pub enum Shape {
    Chain,
    Star,
    Balanced,
    Random,
}

/// A tree of `n` nodes of the given shape, with node ids a random sample of 0..1000 (so that
/// "lower id initiates" meets every structure).
pub fn tree(shape: Shape, n: usize, rng: &mut ChaCha8Rng) -> Topology {
    let mut pool: Vec<u32> = (0..1000).collect();
    pool.shuffle(rng);
    let ids: Vec<NodeId> = pool[..n].iter().map(|&i| NodeId(i)).collect();
    let parent = |i: usize, rng: &mut ChaCha8Rng| -> usize {
        match shape {
            Shape::Chain => i - 1,
            Shape::Star => 0,
            Shape::Balanced => (i - 1) / 2,
            Shape::Random => rng.random_range(0..i),
        }
    };
    let links: Vec<(NodeId, NodeId)> = (1..n).map(|i| (ids[parent(i, rng)], ids[i])).collect();
    Topology::tree(ids, links).expect("generated trees are trees")
}

/// Feature ground truth: positions relative to nothing in particular (absolute coordinates
/// near the origin).
pub fn features(n: usize, rng: &mut ChaCha8Rng) -> Vec<(FeatureId, Vector3<f64>)> {
    (0..n)
        .map(|k| {
            let p = origin() + Vector3::from_fn(|_, _| rng.random_range(-500.0..500.0));
            (1000 + 7 * k as FeatureId, p)
        })
        .collect()
}

/// A random SPD 3 × 3 measurement covariance with standard deviations in [0.5, 5] m.
fn random_r(rng: &mut ChaCha8Rng) -> Matrix3<f64> {
    let q = nalgebra::Rotation3::from_euler_angles(
        rng.random_range(-3.0..3.0),
        rng.random_range(-1.5..1.5),
        rng.random_range(-3.0..3.0),
    );
    let d = Matrix3::from_diagonal(&Vector3::from_fn(|_, _| {
        rng.random_range(0.5f64..5.0).powi(2)
    }));
    let r = q.matrix() * d * q.matrix().transpose();
    (r + r.transpose()) * 0.5
}

/// Information of one direct observation z = m_f + v, v ~ N(0, R) (H = I on feature f):
/// Y_ff = R⁻¹, y_f = R⁻¹ (z − o).
pub fn direct_observation(
    id: FeatureId,
    truth: &Vector3<f64>,
    rng: &mut ChaCha8Rng,
) -> MapInformation {
    let r = random_r(rng);
    let l = r.cholesky().expect("SPD").l();
    let noise = l * Vector3::from_fn(|_, _| rng.sample::<f64, _>(rand_distr::StandardNormal));
    let z = truth + noise;
    let yi = r.try_inverse().expect("SPD");
    let yi = (yi + yi.transpose()) * 0.5;
    let yv = yi * (z - origin());
    MapInformation {
        ids: vec![id],
        origin: origin(),
        matrix: Mat::from_fn(3, 3, |i, j| yi[(i, j)]),
        vector: Col::from_fn(3, |i| yv[i]),
    }
}

/// Information of one relative observation z = m_f − m_g + v (H = [I, −I]): couples two
/// features, so the map information has off-diagonal blocks.
pub fn relative_observation(
    (f, pf): (FeatureId, &Vector3<f64>),
    (g, pg): (FeatureId, &Vector3<f64>),
    rng: &mut ChaCha8Rng,
) -> MapInformation {
    let r = random_r(rng);
    let l = r.cholesky().expect("SPD").l();
    let noise = l * Vector3::from_fn(|_, _| rng.sample::<f64, _>(rand_distr::StandardNormal));
    let z = pf - pg + noise;
    let yi = r.try_inverse().expect("SPD");
    let yi = (yi + yi.transpose()) * 0.5;
    // Hᵀ R⁻¹ H = [[R⁻¹, −R⁻¹], [−R⁻¹, R⁻¹]]; Hᵀ R⁻¹ z' with z' = z − (H o) = z (H o = 0).
    let yv = yi * z;
    let mut matrix = Mat::zeros(6, 6);
    for i in 0..3 {
        for j in 0..3 {
            matrix[(i, j)] = yi[(i, j)];
            matrix[(i + 3, j + 3)] = yi[(i, j)];
            matrix[(i, j + 3)] = -yi[(i, j)];
            matrix[(i + 3, j)] = -yi[(i, j)];
        }
    }
    MapInformation {
        ids: vec![f, g],
        origin: origin(),
        matrix,
        vector: Col::from_fn(6, |i| if i < 3 { yv[i] } else { -yv[i - 3] }),
    }
}

/// Random observations of a node: direct observations of a random subset of the features, and
/// (if `relative`) one relative observation between two of them.
pub fn random_observations(
    feats: &[(FeatureId, Vector3<f64>)],
    rng: &mut ChaCha8Rng,
    relative: bool,
) -> MapInformation {
    let mut info = MapInformation::zero(origin());
    let k = rng.random_range(1..=feats.len().min(5));
    let picked: Vec<&(FeatureId, Vector3<f64>)> = feats.choose_multiple(rng, k).collect();
    for (id, p) in &picked {
        info.add_assign(&direct_observation(*id, p, rng)).unwrap();
    }
    if relative && picked.len() >= 2 {
        let (a, b) = (picked[0], picked[1]);
        info.add_assign(&relative_observation((a.0, &a.1), (b.0, &b.1), rng))
            .unwrap();
    }
    info
}

/// Fault model of the simulated links (probabilities per message).
#[derive(Clone, Copy, Debug, Default)]
pub struct Faults {
    /// Probability that a message is lost.
    pub loss: f64,
    /// Probability that a message is delivered twice.
    pub duplicate: f64,
    /// Delay, uniform in 0..=max_delay rounds (independent per copy: reorders).
    pub max_delay: u64,
}

/// One simulated process.
pub struct SimNode {
    pub ddf: DdfNode,
    /// Y_i: the stand-in for the EKF's map (an information accumulator).
    pub estimate: MapInformation,
    /// What this incarnation observed itself.
    pub own: MapInformation,
}

struct InFlight {
    deliver_at: u64,
    order: u64,
    from: NodeId,
    to: NodeId,
    bytes: Vec<u8>,
}

/// A lock-step network: each round every node runs `on_round`, then messages due are delivered
/// (replies with zero delay within the same round). Every message goes through the bincode
/// wire form.
pub struct Sim {
    pub topology: Topology,
    pub mode: Mode,
    pub config: DdfConfig,
    pub nodes: BTreeMap<NodeId, SimNode>,
    in_flight: Vec<InFlight>,
    order: u64,
    pub round: u64,
    rng: ChaCha8Rng,
    pub faults: Faults,
    down: BTreeMap<(NodeId, NodeId), bool>,
    /// Everything ever observed by any incarnation: the centralized filter's information.
    pub all_ever: MapInformation,
    pub delivered: u64,
    pub bytes: u64,
    /// Cross-vehicle association for keyed runs (`ddf_keys`): `None` = keys are identities.
    pub oracle: Option<Oracle>,
}

/// The truth behind per-node keys, and how eagerly a receiver associates a key it does not
/// hold with one of its own (a correspondence proposed with probability `p` per delta).
pub struct Oracle {
    /// Every key → the true feature it names.
    pub truth: BTreeMap<FeatureId, FeatureId>,
    /// Probability of associating an unknown key when a delta carries it.
    pub p: f64,
    /// Test-only broken variant: the receiver "merges" by copying the information of the other
    /// key onto its own instead of moving it (both keys keep it: counted twice).
    pub copy_instead_of_move: bool,
    /// Merges adopted (proposed and accepted).
    pub proposed: u64,
}

impl Oracle {
    /// The key map that merges every key of a true feature (the centralized view).
    pub fn truth_keys(&self) -> KeyMap {
        let mut k = KeyMap::default();
        let mut first: BTreeMap<FeatureId, FeatureId> = BTreeMap::new();
        for (&key, &f) in &self.truth {
            match first.get(&f) {
                Some(&other) => {
                    k.adopt(key, other);
                }
                None => {
                    first.insert(f, key);
                }
            }
        }
        k
    }
}

/// The estimate as seen by a node whose receiver associates keys by the oracle.
struct Associating<'a> {
    estimate: &'a mut MapInformation,
    oracle: &'a mut Oracle,
    rng: &'a mut ChaCha8Rng,
}

impl FuseTarget for Associating<'_> {
    fn fuse(&mut self, delta: &MapInformation) -> Result<(), FuseRejected> {
        self.estimate.fuse(delta)
    }
    fn fuse_submap(&mut self, s: &Submap, c: CiCriterion) -> Result<(), FuseRejected> {
        self.estimate.fuse_submap(s, c)
    }
    fn merge(&mut self, m: &Merge) -> Result<(), FuseRejected> {
        self.estimate.merge(m)
    }
    fn associate(&mut self, delta: &MapInformation) -> Vec<Merge> {
        let held: BTreeMap<FeatureId, FeatureId> = self
            .estimate
            .ids
            .iter()
            .map(|&k| (self.oracle.truth[&k], k))
            .collect();
        let mut out = Vec::new();
        for &k in &delta.ids {
            if self.estimate.ids.contains(&k) {
                continue;
            }
            if let Some(&mine) = held.get(&self.oracle.truth[&k])
                && self.rng.random_bool(self.oracle.p)
                && let Some(m) = Merge::of(k, mine)
            {
                self.oracle.proposed += 1;
                if self.oracle.copy_instead_of_move {
                    // The delta's information on k, re-labelled as `mine`, added on top.
                    let mut copy = delta.restrict(&[k]);
                    copy.ids = vec![mine];
                    self.estimate.add_assign(&copy).unwrap();
                } else {
                    out.push(m);
                }
            }
        }
        out
    }
}

fn key(a: NodeId, b: NodeId) -> (NodeId, NodeId) {
    (a.min(b), a.max(b))
}

impl Sim {
    pub fn new(topology: Topology, mode: Mode, config: DdfConfig, seed: u64) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let nodes = topology
            .nodes()
            .iter()
            .map(|&id| {
                let ddf =
                    DdfNode::for_mode(mode, id, rng.random(), &topology, origin(), config.clone())
                        .expect("valid topology for the mode");
                let zero = MapInformation::zero(origin());
                (
                    id,
                    SimNode {
                        ddf,
                        estimate: zero.clone(),
                        own: zero,
                    },
                )
            })
            .collect();
        Sim {
            topology,
            mode,
            config,
            nodes,
            in_flight: Vec::new(),
            order: 0,
            round: 0,
            rng,
            faults: Faults::default(),
            down: BTreeMap::new(),
            all_ever: MapInformation::zero(origin()),
            delivered: 0,
            bytes: 0,
            oracle: None,
        }
    }

    fn now(&self) -> f64 {
        self.round as f64
    }

    /// Reports every link up at both ends (the start of a run).
    pub fn link_all_up(&mut self) {
        let ids: Vec<NodeId> = self.nodes.keys().copied().collect();
        for id in ids {
            let peers: Vec<NodeId> = self.nodes[&id].ddf.neighbours().collect();
            for p in peers {
                let now = self.now();
                let out = self
                    .nodes
                    .get_mut(&id)
                    .unwrap()
                    .ddf
                    .on_link_up(now, p)
                    .unwrap();
                for o in out {
                    self.send(id, o.to, &o.message);
                }
            }
        }
    }

    /// Adds an observation to a node's estimate (its EKF update) and to the central reference.
    pub fn observe(&mut self, node: NodeId, info: &MapInformation) {
        let n = self.nodes.get_mut(&node).unwrap();
        n.estimate.add_assign(info).unwrap();
        n.own.add_assign(info).unwrap();
        self.all_ever.add_assign(info).unwrap();
    }

    fn send(&mut self, from: NodeId, to: NodeId, msg: &DdfMessage) {
        if self.down.get(&key(from, to)).copied().unwrap_or(false) {
            return;
        }
        let bytes = bincode::serde::encode_to_vec(msg, bincode::config::standard()).unwrap();
        self.bytes += bytes.len() as u64;
        if self.rng.random_bool(self.faults.loss) {
            return;
        }
        let copies = if self.rng.random_bool(self.faults.duplicate) {
            2
        } else {
            1
        };
        for _ in 0..copies {
            let delay = self.rng.random_range(0..=self.faults.max_delay);
            self.order += 1;
            self.in_flight.push(InFlight {
                deliver_at: self.round + delay,
                order: self.order,
                from,
                to,
                bytes: bytes.clone(),
            });
        }
    }

    /// Delivers everything due now, including zero-delay replies.
    fn deliver(&mut self) {
        for _ in 0..10_000 {
            self.in_flight.sort_by_key(|m| (m.deliver_at, m.order));
            let Some(pos) = self
                .in_flight
                .iter()
                .position(|m| m.deliver_at <= self.round)
            else {
                return;
            };
            let m = self.in_flight.remove(pos);
            if self.down.get(&key(m.from, m.to)).copied().unwrap_or(false) {
                continue; // lost in the outage
            }
            let (msg, _): (DdfMessage, usize) =
                bincode::serde::decode_from_slice(&m.bytes, bincode::config::standard()).unwrap();
            let now = self.now();
            let node = self.nodes.get_mut(&m.to).unwrap();
            let result = match self.oracle.as_mut() {
                None => node.ddf.on_message(now, m.from, msg, &mut node.estimate),
                Some(oracle) => {
                    let mut target = Associating {
                        estimate: &mut node.estimate,
                        oracle,
                        rng: &mut self.rng,
                    };
                    node.ddf.on_message(now, m.from, msg, &mut target)
                }
            };
            let out = result
                .unwrap_or_else(|e| panic!("round {}: {} → {}: {e}", self.round, m.from, m.to));
            self.delivered += 1;
            for o in out {
                self.send(m.to, o.to, &o.message);
            }
        }
        panic!("message storm: replies never settle");
    }

    /// One round: every node's `on_round` (in id order), then delivery of what is due.
    pub fn round(&mut self) {
        let now = self.now();
        let ids: Vec<NodeId> = self.nodes.keys().copied().collect();
        for id in ids {
            let node = self.nodes.get_mut(&id).unwrap();
            let out = node.ddf.on_round(now, &mut node.estimate).unwrap();
            for o in out.messages {
                self.send(id, o.to, &o.message);
            }
        }
        self.deliver();
        self.round += 1;
    }

    /// Takes a link down or up at both ends (messages in flight on it are lost while down).
    pub fn set_link(&mut self, a: NodeId, b: NodeId, up: bool) {
        self.down.insert(key(a, b), !up);
        let now = self.now();
        for (x, y) in [(a, b), (b, a)] {
            let ddf = &mut self.nodes.get_mut(&x).unwrap().ddf;
            if up {
                let out = ddf.on_link_up(now, y).unwrap();
                for o in out {
                    self.send(x, o.to, &o.message);
                }
            } else {
                ddf.on_link_down(y).unwrap();
            }
        }
    }

    /// Restarts a node's process: new epoch, empty estimate, links reported up.
    pub fn restart(&mut self, id: NodeId) {
        let epoch = self.rng.random();
        let ddf = DdfNode::for_mode(
            self.mode,
            id,
            epoch,
            &self.topology,
            origin(),
            self.config.clone(),
        )
        .unwrap();
        let zero = MapInformation::zero(origin());
        self.nodes.insert(
            id,
            SimNode {
                ddf,
                estimate: zero.clone(),
                own: zero,
            },
        );
        let peers: Vec<NodeId> = self.nodes[&id].ddf.neighbours().collect();
        let now = self.now();
        for p in peers {
            if !self.down.get(&key(id, p)).copied().unwrap_or(false) {
                let out = self
                    .nodes
                    .get_mut(&id)
                    .unwrap()
                    .ddf
                    .on_link_up(now, p)
                    .unwrap();
                for o in out {
                    self.send(id, o.to, &o.message);
                }
            }
        }
    }

    /// Σ of what live incarnations observed: what the network converges to.
    pub fn live_sum(&self) -> MapInformation {
        let mut s = MapInformation::zero(origin());
        for n in self.nodes.values() {
            s.add_assign(&n.own).unwrap();
        }
        s
    }

    /// True when every exact channel has a synchronised epoch pair.
    pub fn all_synced(&self) -> bool {
        self.nodes
            .values()
            .all(|n| n.ddf.channels().all(|c| c.synced))
    }

    /// Runs rounds until all channels are synchronised; returns how many it took.
    pub fn handshake(&mut self, max_rounds: u64) -> u64 {
        self.link_all_up();
        for r in 0..max_rounds {
            if self.all_synced() {
                return r;
            }
            self.round();
        }
        assert!(
            self.all_synced(),
            "handshake did not complete in {max_rounds} rounds"
        );
        max_rounds
    }

    /// Largest relative difference of any node's (Y, y) to `reference`.
    pub fn max_relative_difference(&self, reference: &MapInformation) -> f64 {
        self.nodes
            .values()
            .map(|n| n.estimate.relative_difference(reference).unwrap())
            .fold(0.0, f64::max)
    }

    /// Largest λ_max(Y_node − Y_all) over nodes, relative to max|Y_all|.
    pub fn max_psd_excess(&self) -> f64 {
        let scale = self.all_ever.matrix_norm_max().max(f64::MIN_POSITIVE);
        self.nodes
            .values()
            .map(|n| n.estimate.psd_excess_over(&self.all_ever).unwrap() / scale)
            .fold(f64::NEG_INFINITY, f64::max)
    }

    /// Messages still in flight.
    pub fn in_flight(&self) -> usize {
        self.in_flight.len()
    }
}
