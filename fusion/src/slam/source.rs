//! The filter as the DDF node's estimator ([`MapSource`], [`FuseTarget`]): map information on
//! demand (exact links), covariance blocks and marginals (CI links), fuse-back of deltas and
//! covariance-form CI of submaps.

use super::SlamFilter;
use crate::ci::{CiCriterion, Submap};
use crate::ddf::{FuseRejected, FuseTarget, MapSource};
use crate::info::{InfoError, MapInformation, MapMarginal};
use crate::sensor::FeatureId;
use nalgebra::Matrix3;

impl MapSource for SlamFilter {
    fn information(&mut self) -> Result<MapInformation, InfoError> {
        self.map_information()
            .map_err(|e| InfoError::Estimator(e.to_string()))
    }

    fn feature_covariances(&self) -> Vec<(FeatureId, Matrix3<f64>)> {
        // Map blocks are never changed by prediction: no flush needed.
        self.layout
            .features()
            .map(|(id, off)| (id, Matrix3::from_fn(|i, j| self.p[(off + i, off + j)])))
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

impl FuseTarget for SlamFilter {
    fn fuse(&mut self, delta: &MapInformation) -> Result<(), FuseRejected> {
        self.fuse_map_information(delta)
            .map(|_| ())
            .map_err(|e| FuseRejected {
                reason: e.to_string(),
            })
    }

    fn fuse_submap(&mut self, submap: &Submap, criterion: CiCriterion) -> Result<(), FuseRejected> {
        self.fuse_submap_ci(submap, criterion)
            .map(|_| ())
            .map_err(|e| FuseRejected {
                reason: e.to_string(),
            })
    }
}
