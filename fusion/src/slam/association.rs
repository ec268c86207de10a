//! Data association (§21.3.3): the Mahalanobis gate of eq. 21.55, by descriptor, greedy nearest
//! neighbour, or joint compatibility branch and bound (JCBB, Neira & Tardós 2001).

use super::{AssociationMode, ObservationOutcome, RejectReason, SlamFilter};
use crate::observation::{ObservationError, ObservationModel, SensorPose};
use crate::sensor::{FeatureId, SensorModel};
use crate::state::{ATT, POS};
use nalgebra::{DMatrix, DVector, SMatrix};
use std::collections::HashSet;

type Mat6 = SMatrix<f64, 6, 6>;
type Mat6x3 = SMatrix<f64, 6, 3>;

/// An (observation, feature) pairing with its linearization at the prior.
#[derive(Clone, Debug)]
pub(super) struct UpdateItem {
    /// Observation index in the frame.
    pub obs: usize,
    /// Feature id.
    pub feature: FeatureId,
    /// Feature offset in the state.
    pub offset: usize,
    /// ν = z − H(x̂) (azimuth wrapped).
    pub innovation: DVector<f64>,
    /// ∂H/∂(p, Ψ) (d×6).
    pub h_vehicle: DMatrix<f64>,
    /// ∂H/∂m (d×3).
    pub h_feature: DMatrix<f64>,
    /// P_{(p,Ψ), m} (6×3).
    pub p_vm: Mat6x3,
    /// Individual innovation covariance S (d×d).
    pub s: DMatrix<f64>,
    /// Individual NIS νᵀ S⁻¹ ν (∞ if S is not positive definite).
    pub nis: f64,
}

/// The outcome of association for one frame.
#[derive(Clone, Debug, Default)]
pub(super) struct AssociationPlan {
    pub outcomes: Vec<ObservationOutcome>,
    pub updates: Vec<UpdateItem>,
    pub initializations: Vec<usize>,
    pub jcbb_nodes: usize,
    pub jcbb_truncated: bool,
}

fn nis(nu: &DVector<f64>, s: &DMatrix<f64>) -> f64 {
    match s.clone().cholesky() {
        Some(c) => nu.dot(&c.solve(nu)),
        None => f64::INFINITY,
    }
}

/// Shared per-frame data.
struct FrameContext<'a> {
    model: &'a ObservationModel,
    pose: SensorPose,
    voff: usize,
    /// P_{(p,Ψ),(p,Ψ)} (6×6).
    p_vv: Mat6,
    r: DMatrix<f64>,
}

impl SlamFilter {
    /// Indices of the vehicle's (p, Ψ) states: the only vehicle states H depends on.
    fn pose_index(voff: usize, k: usize) -> usize {
        if k < 3 {
            voff + POS + k
        } else {
            voff + ATT + k - 3
        }
    }

    fn candidate(
        &self,
        ctx: &FrameContext<'_>,
        obs: usize,
        z: &DVector<f64>,
        feature: FeatureId,
        offset: usize,
    ) -> Result<UpdateItem, ObservationError> {
        let m = self.vec3_at(offset);
        let pred = ctx.model.predict(&ctx.pose, &m)?;
        let d = pred.z.len();
        let innovation = ctx.model.innovation(z, &pred.z);
        let h_vehicle = DMatrix::from_fn(d, 6, |i, j| {
            if j < 3 {
                pred.d_position[(i, j)]
            } else {
                pred.d_attitude[(i, j - 3)]
            }
        });
        let h_feature = DMatrix::from_fn(d, 3, |i, j| pred.d_feature[(i, j)]);
        let p_vm = Mat6x3::from_fn(|i, j| self.p[(Self::pose_index(ctx.voff, i), offset + j)]);
        let p_mm = DMatrix::from_fn(3, 3, |i, j| self.p[(offset + i, offset + j)]);
        let p_vv = DMatrix::from_fn(6, 6, |i, j| ctx.p_vv[(i, j)]);
        let p_vm_d = DMatrix::from_fn(6, 3, |i, j| p_vm[(i, j)]);
        let cross = &h_vehicle * &p_vm_d * h_feature.transpose();
        let s = &h_vehicle * &p_vv * h_vehicle.transpose()
            + &cross
            + cross.transpose()
            + &h_feature * &p_mm * h_feature.transpose()
            + &ctx.r;
        let nis = nis(&innovation, &s);
        Ok(UpdateItem {
            obs,
            feature,
            offset,
            innovation,
            h_vehicle,
            h_feature,
            p_vm,
            s,
            nis,
        })
    }

    /// Associates every observation of a frame against the prior (see [`AssociationMode`]).
    pub(super) fn associate(
        &mut self,
        vehicle: usize,
        model: &ObservationModel,
        zs: &[DVector<f64>],
        descriptors: &[FeatureId],
    ) -> AssociationPlan {
        let voff = self.layout.vehicle_offset(vehicle);
        let state = self
            .vehicle_state(vehicle)
            .expect("vehicle validated by the caller");
        let ctx = FrameContext {
            model,
            pose: model.sensor_pose(&state.position, &state.attitude),
            voff,
            p_vv: Mat6::from_fn(|i, j| {
                self.p[(Self::pose_index(voff, i), Self::pose_index(voff, j))]
            }),
            r: model.noise_covariance(),
        };
        let d = model.measurement_dim();
        let gate = self.gate(d);
        let can_init = matches!(model.sensor, SensorModel::RangeBearing { .. });
        let mut plan = AssociationPlan {
            outcomes: vec![ObservationOutcome::Rejected(RejectReason::NotInitializable); zs.len()],
            ..Default::default()
        };
        let unmatched = |plan: &mut AssociationPlan, i: usize| {
            if can_init {
                plan.initializations.push(i);
            } else {
                plan.outcomes[i] = ObservationOutcome::Rejected(RejectReason::NotInitializable);
            }
        };
        match self.config.association.mode {
            AssociationMode::Descriptor => {
                let mut seen = HashSet::new();
                for (i, z) in zs.iter().enumerate() {
                    let id = descriptors[i];
                    if !seen.insert(id) {
                        plan.outcomes[i] = ObservationOutcome::Rejected(RejectReason::Ambiguous);
                        continue;
                    }
                    let Some(offset) = self.layout.feature_offset(id) else {
                        unmatched(&mut plan, i);
                        continue;
                    };
                    match self.candidate(&ctx, i, z, id, offset) {
                        Err(_) => {
                            plan.outcomes[i] =
                                ObservationOutcome::Rejected(RejectReason::DegenerateGeometry)
                        }
                        Ok(c) if c.nis <= gate => {
                            plan.outcomes[i] = ObservationOutcome::Associated {
                                feature: id,
                                nis: c.nis,
                            };
                            plan.updates.push(c);
                        }
                        Ok(c) => {
                            plan.outcomes[i] =
                                ObservationOutcome::Rejected(RejectReason::GateFailed {
                                    feature: id,
                                    nis: c.nis,
                                })
                        }
                    }
                }
            }
            AssociationMode::NearestNeighbour | AssociationMode::Jcbb { .. } => {
                let features: Vec<(FeatureId, usize)> = self.layout.features().collect();
                let mut cands: Vec<Vec<UpdateItem>> = zs
                    .iter()
                    .enumerate()
                    .map(|(i, z)| {
                        let mut v: Vec<UpdateItem> = features
                            .iter()
                            .filter_map(|&(id, off)| self.candidate(&ctx, i, z, id, off).ok())
                            .filter(|c| c.nis <= gate)
                            .collect();
                        v.sort_by(|a, b| a.nis.total_cmp(&b.nis));
                        v
                    })
                    .collect();
                let chosen: Vec<Option<usize>> = match self.config.association.mode {
                    AssociationMode::Jcbb { max_nodes } => {
                        let max_dof = d * zs.len();
                        for dof in 1..=max_dof {
                            self.gate(dof);
                        }
                        let mut search = Jcbb::new(self, &ctx, &cands, max_nodes);
                        search.run();
                        plan.jcbb_nodes = search.nodes;
                        plan.jcbb_truncated = search.truncated;
                        search.best
                    }
                    _ => greedy_nearest_neighbour(&cands),
                };
                for (i, choice) in chosen.iter().enumerate() {
                    match choice {
                        Some(k) => {
                            let c = cands[i].swap_remove(*k);
                            plan.outcomes[i] = ObservationOutcome::Associated {
                                feature: c.feature,
                                nis: c.nis,
                            };
                            plan.updates.push(c);
                        }
                        None if !cands[i].is_empty() => {
                            plan.outcomes[i] = ObservationOutcome::Rejected(RejectReason::Ambiguous)
                        }
                        None => unmatched(&mut plan, i),
                    }
                }
            }
        }
        plan
    }
}

/// Greedy global nearest neighbour: pairs in increasing NIS, each observation and feature once.
fn greedy_nearest_neighbour(cands: &[Vec<UpdateItem>]) -> Vec<Option<usize>> {
    let mut pairs: Vec<(f64, usize, usize)> = cands
        .iter()
        .enumerate()
        .flat_map(|(i, v)| v.iter().enumerate().map(move |(k, c)| (c.nis, i, k)))
        .collect();
    pairs.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut chosen = vec![None; cands.len()];
    let mut used = HashSet::new();
    for (_, i, k) in pairs {
        if chosen[i].is_none() && !used.contains(&cands[i][k].feature) {
            used.insert(cands[i][k].feature);
            chosen[i] = Some(k);
        }
    }
    chosen
}

/// Joint compatibility branch and bound over the individually compatible candidates.
struct Jcbb<'a> {
    filter: &'a SlamFilter,
    ctx: &'a FrameContext<'a>,
    cands: &'a [Vec<UpdateItem>],
    max_nodes: usize,
    nodes: usize,
    truncated: bool,
    current: Vec<(usize, usize)>,
    used: HashSet<FeatureId>,
    best: Vec<Option<usize>>,
    best_pairs: usize,
    best_nis: f64,
}

impl<'a> Jcbb<'a> {
    fn new(
        filter: &'a SlamFilter,
        ctx: &'a FrameContext<'a>,
        cands: &'a [Vec<UpdateItem>],
        max_nodes: usize,
    ) -> Self {
        Self {
            filter,
            ctx,
            cands,
            max_nodes,
            nodes: 0,
            truncated: false,
            current: Vec::new(),
            used: HashSet::new(),
            best: vec![None; cands.len()],
            best_pairs: 0,
            best_nis: f64::INFINITY,
        }
    }

    fn run(&mut self) {
        self.search(0);
    }

    /// Joint NIS of the current hypothesis: stacked ν and S with the cross-covariances between
    /// pairings (H_a P H_bᵀ through the shared vehicle pose and the features' correlation).
    fn joint_nis(&self) -> f64 {
        let items: Vec<&UpdateItem> = self
            .current
            .iter()
            .map(|&(i, k)| &self.cands[i][k])
            .collect();
        let d = self.ctx.r.nrows();
        let dim = d * items.len();
        let mut s = DMatrix::zeros(dim, dim);
        let mut nu = DVector::zeros(dim);
        let p_vv = DMatrix::from_fn(6, 6, |i, j| self.ctx.p_vv[(i, j)]);
        for (a, ia) in items.iter().enumerate() {
            nu.rows_mut(a * d, d).copy_from(&ia.innovation);
            for (b, ib) in items.iter().enumerate().skip(a) {
                let block = if a == b {
                    ia.s.clone()
                } else {
                    let p_va = DMatrix::from_fn(6, 3, |i, j| ia.p_vm[(i, j)]);
                    let p_vb = DMatrix::from_fn(6, 3, |i, j| ib.p_vm[(i, j)]);
                    let p_ab = DMatrix::from_fn(3, 3, |i, j| {
                        self.filter.p[(ia.offset + i, ib.offset + j)]
                    });
                    &ia.h_vehicle * &p_vv * ib.h_vehicle.transpose()
                        + &ia.h_vehicle * p_vb * ib.h_feature.transpose()
                        + &ia.h_feature * p_va.transpose() * ib.h_vehicle.transpose()
                        + &ia.h_feature * p_ab * ib.h_feature.transpose()
                };
                s.view_mut((a * d, b * d), (d, d)).copy_from(&block);
                if a != b {
                    s.view_mut((b * d, a * d), (d, d))
                        .copy_from(&block.transpose());
                }
            }
        }
        nis(&nu, &s)
    }

    fn search(&mut self, i: usize) {
        if self.nodes >= self.max_nodes {
            self.truncated = true;
            return;
        }
        self.nodes += 1;
        if i == self.cands.len() {
            let pairs = self.current.len();
            let joint = if pairs == 0 { 0.0 } else { self.joint_nis() };
            if pairs > self.best_pairs || (pairs == self.best_pairs && joint < self.best_nis) {
                self.best_pairs = pairs;
                self.best_nis = joint;
                self.best = vec![None; self.cands.len()];
                for &(o, k) in &self.current {
                    self.best[o] = Some(k);
                }
            }
            return;
        }
        for k in 0..self.cands[i].len() {
            let f = self.cands[i][k].feature;
            if self.used.contains(&f) {
                continue;
            }
            self.current.push((i, k));
            let dof = self.ctx.r.nrows() * self.current.len();
            if self.joint_nis() <= self.filter.gates[dof] {
                self.used.insert(f);
                self.search(i + 1);
                self.used.remove(&f);
            }
            self.current.pop();
        }
        // The "observation i is spurious/new" branch, if it can still beat the best hypothesis.
        let remaining = self.cands.len() - i - 1;
        if self.current.len() + remaining > self.best_pairs {
            self.search(i + 1);
        }
    }
}
