//! The filter as the DDF node's estimator ([`MapSource`], [`FuseTarget`]): map information on
//! demand (exact links), covariance blocks and marginals (CI links), fuse-back of deltas and
//! covariance-form CI of submaps.

use super::update::HBlock;
use super::{SlamError, SlamFilter, SlotKind};
use crate::ci::{CiCriterion, Submap};
use crate::ddf::{FuseRejected, FuseTarget, MapSource};
use crate::info::{InfoError, MapInformation, MapMarginal};
use crate::keys::Merge;
use crate::sensor::{Appearance, FeatureId};
use faer::{Col, Mat};
use nalgebra::Matrix3;

impl MapSource for SlamFilter {
    fn information(&mut self) -> Result<MapInformation, InfoError> {
        // The maintained Y itself, given back by `restore_information` (no k × k copy).
        self.take_map_information()
            .map_err(|e| InfoError::Estimator(e.to_string()))
    }

    fn restore_information(&mut self, info: MapInformation) {
        self.restore_map_information(info);
    }

    fn feature_covariances(&self) -> Vec<(FeatureId, Matrix3<f64>)> {
        // Map blocks are never changed by prediction: no flush needed.
        self.layout
            .features()
            .map(|(id, off)| (id, Matrix3::from_fn(|i, j| self.p[(off + i, off + j)])))
            .collect()
    }

    fn descriptors(&self, ids: &[FeatureId]) -> Vec<(FeatureId, Appearance)> {
        ids.iter()
            .filter_map(|&f| self.appearance.of(f).map(|a| (f, a)))
            .collect()
    }

    fn feature_means(&self, ids: &[FeatureId]) -> Vec<(FeatureId, nalgebra::Vector3<f64>)> {
        ids.iter()
            .filter_map(|&id| Some((id, self.vec3_at(self.layout.feature_offset(id)?))))
            .collect()
    }

    fn marginal(&self, ids: &[FeatureId]) -> MapMarginal {
        let picked: Vec<(FeatureId, usize)> = ids
            .iter()
            .filter_map(|&id| self.layout.feature_offset(id).map(|o| (id, o)))
            .collect();
        let rows: Vec<usize> = picked.iter().flat_map(|&(_, o)| o..o + 3).collect();
        let n = rows.len();
        MapMarginal {
            ids: picked.iter().map(|&(id, _)| id).collect(),
            mean: faer::Col::from_fn(n, |r| self.x[rows[r]]),
            covariance: faer::Mat::from_fn(n, n, |r, c| self.p[(rows[r], rows[c])]),
        }
    }
}

fn refused(e: SlamError) -> FuseRejected {
    FuseRejected {
        reason: e.to_string(),
    }
}

impl FuseTarget for SlamFilter {
    fn fuse(&mut self, delta: &MapInformation) -> Result<(), FuseRejected> {
        self.fuse_map_information(delta)
            .map(|_| ())
            .map_err(refused)
    }

    fn fuse_submap(&mut self, submap: &Submap, criterion: CiCriterion) -> Result<(), FuseRejected> {
        self.fuse_submap_ci(submap, criterion)
            .map(|_| ())
            .map_err(refused)
    }

    fn merge(&mut self, merge: &Merge) -> Result<(), FuseRejected> {
        self.merge_features(merge).map_err(refused)
    }

    fn describe(&mut self, features: &[(FeatureId, Appearance)]) {
        for (f, a) in features {
            self.appearance.described(*f, a);
        }
    }
}

impl SlamFilter {
    /// Applies a correspondence (module [`crate::keys`]): when both keys are features, the
    /// constraint x_from = x_into is imposed exactly (a Kalman update with H = [I, −I] and
    /// R = 0, eqs. 21.56–21.60) and `from` is marginalised out (its rows and columns cut):
    /// the information of the rest is Tᵀ Y T, the merge of design.md §8. When only `from` is
    /// held it is renamed `into`; otherwise nothing changes. Tracks keyed by `from` follow.
    /// On error (the two features' difference has no positive variance) nothing changes.
    pub fn merge_features(&mut self, merge: &Merge) -> Result<(), SlamError> {
        let (from, into) = (merge.from, merge.into);
        let (Some(a), b) = (
            self.layout.feature_offset(from),
            self.layout.feature_offset(into),
        ) else {
            return Ok(());
        };
        self.bearing.rename_descriptor(from, into);
        self.appearance.merge(from, into);
        let Some(b) = b else {
            self.layout.rename_feature(from, into);
            self.bump_map_generation(false);
            return Ok(());
        };
        self.flush();
        let blocks = [
            HBlock {
                row: 0,
                col: a,
                mat: Mat::identity(3, 3),
            },
            HBlock {
                row: 0,
                col: b,
                mat: -Mat::<f64>::identity(3, 3),
            },
        ];
        let nu = Col::from_fn(3, |i| self.x[b + i] - self.x[a + i]);
        self.bump_map_generation(false);
        self.blocks_update(&blocks, &nu, Mat::zeros(3, 3))?;
        self.remove_block(SlotKind::Feature(from));
        Ok(())
    }
}
