//! Data association (§21.3.3): the Mahalanobis gate of eq. 21.55, by descriptor, greedy nearest
//! neighbour, or joint compatibility branch and bound (JCBB, Neira & Tardós 2001).

use super::{AssociationMode, ObservationOutcome, RejectReason, SlamFilter};
use crate::consistency::chi2_quantile;
use crate::observation::{ObservationError, ObservationModel, SensorPose};
use crate::sensor::FeatureId;
use crate::sensor::SensorModel;
use crate::state::{ATT, POS};
use nalgebra::{DMatrix, DVector, SMatrix, Vector3};
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
    pub jcbb_joint_nis: Option<f64>,
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

    /// A cheap conservative pre-filter for the gating modes (range-bearing only): the observation
    /// back-projected to m_obs = J_1(x̂, z) and tr Cov(m_obs) = tr(∇J_x P ∇J_xᵀ + ∇J_z R ∇J_zᵀ).
    /// To first order ν ≈ H_m (m_obs − m_j) and S = H_m Σ H_mᵀ with Σ = Cov(m_obs − m_j)
    /// ⪯ 2 (Cov(m_obs) + P_jj), so NIS ≥ |m_obs − m_j|² / (2 (tr Cov(m_obs) + tr P_jj)): a
    /// feature farther than that cannot pass the gate and its prediction is skipped.
    fn prefilter_bound(
        &self,
        ctx: &FrameContext<'_>,
        z: &DVector<f64>,
    ) -> Option<(Vector3<f64>, f64)> {
        let init = ctx.model.initialize(&ctx.pose, z).ok()?;
        let jx = SMatrix::<f64, 3, 6>::from_fn(|i, j| {
            if j < 3 {
                init.d_position[(i, j)]
            } else {
                init.d_attitude[(i, j - 3)]
            }
        });
        let jz = DMatrix::from_fn(3, 3, |i, j| init.d_measurement[(i, j)]);
        let tr_x = (jx * ctx.p_vv * jx.transpose()).trace();
        let tr_z = (&jz * &ctx.r * jz.transpose()).trace();
        Some((init.feature, tr_x + tr_z))
    }

    /// Associates every observation of a frame against the prior (see [`AssociationMode`]).
    pub(super) fn associate(
        &mut self,
        vehicle: usize,
        model: &ObservationModel,
        zs: &[DVector<f64>],
        descriptors: &[FeatureId],
        appearances: &[Option<crate::sensor::Appearance>],
    ) -> AssociationPlan {
        let voff = self.layout.vehicle_block(vehicle);
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
        // The wider "is it new?" gate (at least the validation gate).
        let new_gate = chi2_quantile(d as f64, self.config.association.new_feature_probability)
            .unwrap_or(f64::INFINITY)
            .max(gate);
        let mut plan = AssociationPlan {
            outcomes: vec![ObservationOutcome::Rejected(RejectReason::NotInitializable); zs.len()],
            ..Default::default()
        };
        // Unmatched observations initialize features: directly for range-bearing sensors,
        // through the bearing-only tracks otherwise (the filter routes them).
        let unmatched = |plan: &mut AssociationPlan, i: usize| {
            plan.initializations.push(i);
        };
        match self.config.association.mode {
            AssociationMode::Descriptor => {
                // The marginal-error outlier test applies to bearing and pixel sensors.
                let marginal_ratio = if matches!(model.sensor, SensorModel::RangeBearing { .. }) {
                    1.0
                } else {
                    self.bearing.config.marginal_sigma_ratio
                };
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
                        Ok(c) => {
                            // A gross outlier against the observation's own (marginal) error
                            // (`BearingConfig::marginal_sigma_ratio`), reported with that NIS.
                            let marginal = (marginal_ratio < 1.0).then(|| {
                                let shrink = 1.0 - marginal_ratio * marginal_ratio;
                                nis(&c.innovation, &(&c.s - &ctx.r * shrink))
                            });
                            match marginal {
                                Some(m) if m > new_gate => {
                                    plan.outcomes[i] =
                                        ObservationOutcome::Rejected(RejectReason::GateFailed {
                                            feature: id,
                                            nis: m,
                                        })
                                }
                                _ if c.nis <= gate => {
                                    plan.outcomes[i] = ObservationOutcome::Associated {
                                        feature: id,
                                        nis: c.nis,
                                    };
                                    plan.updates.push(c);
                                }
                                _ => {
                                    plan.outcomes[i] =
                                        ObservationOutcome::Rejected(RejectReason::GateFailed {
                                            feature: id,
                                            nis: c.nis,
                                        })
                                }
                            }
                        }
                    }
                }
            }
            AssociationMode::NearestNeighbour
            | AssociationMode::Jcbb { .. }
            | AssociationMode::Appearance { .. } => {
                let features: Vec<(FeatureId, usize, Vector3<f64>, f64)> = self
                    .layout
                    .features()
                    .map(|(id, off)| {
                        let trace = (0..3).map(|c| self.p[(off + c, off + c)]).sum();
                        (id, off, self.vec3_at(off), trace)
                    })
                    .collect();
                // Appearance mode: a track that follows a feature is tried against it alone;
                // other observations against features that look alike (and, like every gating
                // mode, are close enough to pass the gate).
                let looks = match self.config.association.mode {
                    AssociationMode::Appearance { max_distance, .. } => Some(max_distance),
                    _ => None,
                };
                let mut repeated = HashSet::new();
                let mut seen_tracks = HashSet::new();
                for (i, &t) in descriptors.iter().enumerate() {
                    if looks.is_some() && !seen_tracks.insert(t) {
                        repeated.insert(i);
                    }
                }
                // Per observation: the nearest feature inside the wider new-feature gate.
                let mut near: Vec<Option<(FeatureId, f64)>> = vec![None; zs.len()];
                let mut cands: Vec<Vec<UpdateItem>> = zs
                    .iter()
                    .enumerate()
                    .map(|(i, z)| {
                        if repeated.contains(&i) {
                            return Vec::new();
                        }
                        if looks.is_some()
                            && let Some(f) = self.appearance.linked(vehicle, descriptors[i])
                            && let Some(off) = self.layout.feature_offset(f)
                            && let Ok(c) = self.candidate(&ctx, i, z, f, off)
                            && c.nis <= gate
                        {
                            near[i] = Some((f, c.nis));
                            return vec![c];
                        }
                        let bound = self.prefilter_bound(&ctx, z);
                        let mut v: Vec<UpdateItem> = features
                            .iter()
                            .filter(|(id, _, _, _)| match looks {
                                None => true,
                                Some(max) => self
                                    .appearance
                                    .distance(&appearances[i], *id)
                                    .is_some_and(|d| d <= max),
                            })
                            .filter(|(_, _, m, trace)| match &bound {
                                // 4× the linearized bound: margin for nonlinearity.
                                Some((m_obs, tr_obs)) => {
                                    (m_obs - m).norm_squared()
                                        <= 4.0 * new_gate * 2.0 * (tr_obs + trace)
                                }
                                None => true,
                            })
                            .filter_map(|&(id, off, _, _)| self.candidate(&ctx, i, z, id, off).ok())
                            .filter(|c| c.nis <= new_gate)
                            .collect();
                        v.sort_by(|a, b| a.nis.total_cmp(&b.nis));
                        near[i] = v.first().map(|c| (c.feature, c.nis));
                        v.retain(|c| c.nis <= gate);
                        v
                    })
                    .collect();
                let chosen: Vec<Option<usize>> = match self.config.association.mode {
                    AssociationMode::Jcbb { max_nodes }
                    | AssociationMode::Appearance { max_nodes, .. } => {
                        let max_dof = d * zs.len();
                        for dof in 1..=max_dof {
                            self.gate(dof);
                        }
                        let mut search = Jcbb::new(self, &ctx, &cands, max_nodes);
                        search.run();
                        plan.jcbb_nodes = search.nodes;
                        plan.jcbb_truncated = search.truncated;
                        plan.jcbb_joint_nis = (search.best_pairs > 0).then_some(search.best_nis);
                        search.best
                    }
                    _ => greedy_nearest_neighbour(&cands),
                };
                for (i, choice) in chosen.iter().enumerate() {
                    if repeated.contains(&i) {
                        plan.outcomes[i] = ObservationOutcome::Rejected(RejectReason::Ambiguous);
                        continue;
                    }
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
                        None => match near[i] {
                            // Outside the validation gate but too close to call it new.
                            Some((feature, nis)) => {
                                plan.outcomes[i] =
                                    ObservationOutcome::Rejected(RejectReason::GateFailed {
                                        feature,
                                        nis,
                                    })
                            }
                            None => unmatched(&mut plan, i),
                        },
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
///
/// The joint innovation covariance of the hypothesis on the current search path is kept as a
/// growing lower Cholesky factor L with w = L⁻¹ν, so adding a pairing c costs one block row:
/// X = L⁻¹ S_{·c}, L_cc = chol(S_cc − XᵀX), w_c = L_cc⁻¹(ν_c − Xᵀw), NIS += |w_c|² (O(k²) per
/// node instead of re-factorizing the whole joint S).
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
    /// Lower Cholesky factor of the path's joint S (leading d·depth block valid).
    l: DMatrix<f64>,
    /// L⁻¹ ν along the path.
    w: DVector<f64>,
    /// Joint NIS at each depth (index 0 = empty hypothesis).
    nis_path: Vec<f64>,
    p_vv: DMatrix<f64>,
}

impl<'a> Jcbb<'a> {
    fn new(
        filter: &'a SlamFilter,
        ctx: &'a FrameContext<'a>,
        cands: &'a [Vec<UpdateItem>],
        max_nodes: usize,
    ) -> Self {
        let dim = ctx.r.nrows() * cands.len();
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
            l: DMatrix::zeros(dim, dim),
            w: DVector::zeros(dim),
            nis_path: vec![0.0],
            p_vv: DMatrix::from_fn(6, 6, |i, j| ctx.p_vv[(i, j)]),
        }
    }

    fn run(&mut self) {
        self.search(0);
    }

    /// Cross-covariance H_c P H_aᵀ of two pairings (through the shared vehicle pose and the
    /// features' correlation).
    fn cross(&self, c: &UpdateItem, a: &UpdateItem) -> DMatrix<f64> {
        let p_vc = DMatrix::from_fn(6, 3, |i, j| c.p_vm[(i, j)]);
        let p_va = DMatrix::from_fn(6, 3, |i, j| a.p_vm[(i, j)]);
        let p_ca = DMatrix::from_fn(3, 3, |i, j| self.filter.p[(c.offset + i, a.offset + j)]);
        &c.h_vehicle * &self.p_vv * a.h_vehicle.transpose()
            + &c.h_vehicle * p_va * a.h_feature.transpose()
            + &c.h_feature * p_vc.transpose() * a.h_vehicle.transpose()
            + &c.h_feature * p_ca * a.h_feature.transpose()
    }

    /// Extends the path's factor by pairing (i, k); returns the new joint NIS, or `None` if the
    /// joint S would not be positive definite. Writes only rows beyond the current depth.
    fn extend(&mut self, i: usize, k: usize) -> Option<f64> {
        let d = self.ctx.r.nrows();
        let depth = self.current.len();
        let dim = d * depth;
        let c = &self.cands[i][k];
        let mut x = DMatrix::zeros(dim, d);
        for (a, &(ia, ka)) in self.current.iter().enumerate() {
            let blk = self.cross(c, &self.cands[ia][ka]);
            x.view_mut((a * d, 0), (d, d)).copy_from(&blk.transpose());
        }
        if dim > 0
            && !self
                .l
                .view((0, 0), (dim, dim))
                .solve_lower_triangular_mut(&mut x)
        {
            return None;
        }
        let schur = &c.s - x.transpose() * &x;
        let l_cc = schur.cholesky()?.l();
        let mut w_c = &c.innovation - x.transpose() * self.w.rows(0, dim);
        if !l_cc.solve_lower_triangular_mut(&mut w_c) {
            return None;
        }
        let nis = self.nis_path[depth] + w_c.norm_squared();
        self.l
            .view_mut((dim, 0), (d, dim))
            .copy_from(&x.transpose());
        self.l.view_mut((dim, dim), (d, d)).copy_from(&l_cc);
        self.w.rows_mut(dim, d).copy_from(&w_c);
        Some(nis)
    }

    fn search(&mut self, i: usize) {
        if self.nodes >= self.max_nodes {
            self.truncated = true;
            return;
        }
        self.nodes += 1;
        if i == self.cands.len() {
            let pairs = self.current.len();
            let joint = self.nis_path[pairs];
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
            let dof = self.ctx.r.nrows() * (self.current.len() + 1);
            match self.extend(i, k) {
                Some(nis) if nis <= self.filter.gates[dof] => {
                    self.current.push((i, k));
                    self.nis_path.push(nis);
                    self.used.insert(f);
                    self.search(i + 1);
                    self.used.remove(&f);
                    self.nis_path.pop();
                    self.current.pop();
                }
                _ => {}
            }
        }
        // The "observation i is spurious/new" branch, if it can still beat the best hypothesis.
        let remaining = self.cands.len() - i - 1;
        if self.current.len() + remaining > self.best_pairs {
            self.search(i + 1);
        }
    }
}
