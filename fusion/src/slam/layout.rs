//! The slot table: the single place that knows where each block lives in x and P.
//!
//! Vehicle blocks come first (15 states each, in vehicle order), then features (3 each, keyed by
//! [`FeatureId`]) in the order they were added, then stored poses (6 each, bearing-only SLAM,
//! eq. 21.67) in the order they were added. [`Layout::push`] appends; a feature appended while
//! poses exist is moved in front of them by [`Layout::poses_last`], which returns the state
//! permutation the filter applies to x and P. Nothing outside this module computes an offset
//! from a count ("15 + 3i"); everything asks the layout.

use crate::sensor::FeatureId;
use crate::state::{FEATURE_DIM, POSE_DIM, VEHICLE_DIM};
use std::collections::HashMap;

/// Id of a stored pose (bearing-only SLAM, eq. 21.66).
pub type PoseId = u64;

/// What a block of the state holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum SlotKind {
    /// Vehicle block `i` (15 states).
    Vehicle(usize),
    /// A map feature (3 states).
    Feature(FeatureId),
    /// A stored vehicle pose p^n, Ψ^n (6 states).
    Pose(PoseId),
}

impl SlotKind {
    /// Number of states of the block.
    pub fn dim(self) -> usize {
        match self {
            SlotKind::Vehicle(_) => VEHICLE_DIM,
            SlotKind::Feature(_) => FEATURE_DIM,
            SlotKind::Pose(_) => POSE_DIM,
        }
    }
}

/// One block of the state: its kind and first index.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Slot {
    /// What the block holds.
    pub kind: SlotKind,
    /// Index of its first state in x (row/column in P).
    pub offset: usize,
}

/// The slot table of a filter.
#[derive(Clone, Debug, Default)]
pub struct Layout {
    slots: Vec<Slot>,
    index: HashMap<SlotKind, usize>,
    num_vehicles: usize,
    dim: usize,
}

impl Layout {
    /// A layout with `vehicles` vehicle blocks and nothing else.
    pub fn new(vehicles: usize) -> Self {
        let mut l = Self::default();
        for v in 0..vehicles {
            l.push(SlotKind::Vehicle(v));
        }
        l.num_vehicles = vehicles;
        l
    }

    /// Total state dimension n.
    pub fn dim(&self) -> usize {
        self.dim
    }

    /// Number of vehicle blocks.
    pub fn num_vehicles(&self) -> usize {
        self.num_vehicles
    }

    /// All slots in state order.
    pub fn slots(&self) -> &[Slot] {
        &self.slots
    }

    /// Offset of a block, if present.
    pub fn offset(&self, kind: SlotKind) -> Option<usize> {
        self.index.get(&kind).map(|&i| self.slots[i].offset)
    }

    /// Offset of vehicle block `v`, if the filter has that vehicle.
    pub fn vehicle_offset(&self, v: usize) -> Option<usize> {
        self.offset(SlotKind::Vehicle(v))
    }

    /// Offset of a vehicle index the filter has already validated.
    pub(crate) fn vehicle_block(&self, v: usize) -> usize {
        self.offset(SlotKind::Vehicle(v))
            .expect("vehicle index validated by the caller")
    }

    /// Offset of a feature, if the filter holds it.
    pub fn feature_offset(&self, id: FeatureId) -> Option<usize> {
        self.offset(SlotKind::Feature(id))
    }

    /// True when the feature is in the state.
    pub fn has_feature(&self, id: FeatureId) -> bool {
        self.index.contains_key(&SlotKind::Feature(id))
    }

    /// Features (id, offset) in state order.
    pub fn features(&self) -> impl Iterator<Item = (FeatureId, usize)> + '_ {
        self.slots.iter().filter_map(|s| match s.kind {
            SlotKind::Feature(id) => Some((id, s.offset)),
            _ => None,
        })
    }

    /// Number of features.
    pub fn num_features(&self) -> usize {
        self.features().count()
    }

    /// Offset of a stored pose, if the filter holds it.
    pub fn pose_offset(&self, id: PoseId) -> Option<usize> {
        self.offset(SlotKind::Pose(id))
    }

    /// Stored poses (id, offset) in state order.
    pub fn poses(&self) -> impl Iterator<Item = (PoseId, usize)> + '_ {
        self.slots.iter().filter_map(|s| match s.kind {
            SlotKind::Pose(id) => Some((id, s.offset)),
            _ => None,
        })
    }

    /// Number of stored poses.
    pub fn num_poses(&self) -> usize {
        self.poses().count()
    }

    /// Restores the order vehicles, features, poses after blocks were appended behind poses:
    /// moves every pose slot behind all other slots (relative orders kept). Returns `None` when
    /// nothing moves, else `(start, order)`: the states before `start` keep their indices and new
    /// state `start + k` is old state `order[k]`.
    pub fn poses_last(&mut self) -> Option<(usize, Vec<usize>)> {
        let first_pose = self
            .slots
            .iter()
            .position(|s| matches!(s.kind, SlotKind::Pose(_)))?;
        // In order iff no non-pose slot follows the first pose.
        let misplaced = self.slots[first_pose..]
            .iter()
            .any(|s| !matches!(s.kind, SlotKind::Pose(_)));
        if !misplaced {
            return None;
        }
        let start = self.slots[first_pose].offset;
        let (mut moved, poses): (Vec<Slot>, Vec<Slot>) = self.slots[first_pose..]
            .iter()
            .partition(|s| !matches!(s.kind, SlotKind::Pose(_)));
        moved.extend(poses);
        let mut order = Vec::with_capacity(self.dim - start);
        let mut offset = start;
        for (k, slot) in moved.iter_mut().enumerate() {
            order.extend(slot.offset..slot.offset + slot.kind.dim());
            slot.offset = offset;
            offset += slot.kind.dim();
            self.index.insert(slot.kind, first_pose + k);
        }
        self.slots.truncate(first_pose);
        self.slots.extend(moved);
        Some((start, order))
    }

    /// Appends a block at the end of the state and returns its offset. Panics if the block is
    /// already present (callers check ids first).
    pub fn push(&mut self, kind: SlotKind) -> usize {
        assert!(
            !self.index.contains_key(&kind),
            "slot {kind:?} already present"
        );
        let offset = self.dim;
        self.index.insert(kind, self.slots.len());
        self.slots.push(Slot { kind, offset });
        self.dim += kind.dim();
        offset
    }

    /// Renames a feature block (a key merged into another that this layout does not hold).
    /// Returns false when `from` is absent or `into` present.
    pub fn rename_feature(&mut self, from: FeatureId, into: FeatureId) -> bool {
        let (f, t) = (SlotKind::Feature(from), SlotKind::Feature(into));
        if self.index.contains_key(&t) {
            return false;
        }
        let Some(i) = self.index.remove(&f) else {
            return false;
        };
        self.slots[i].kind = t;
        self.index.insert(t, i);
        true
    }

    /// Removes a non-vehicle block; later blocks move up. Returns the removed slot (its offset is
    /// the range that must be cut from x and P).
    pub fn remove(&mut self, kind: SlotKind) -> Option<Slot> {
        if matches!(kind, SlotKind::Vehicle(_)) {
            return None;
        }
        let i = self.index.remove(&kind)?;
        let removed = self.slots.remove(i);
        let d = kind.dim();
        for s in &mut self.slots[i..] {
            s.offset -= d;
        }
        for (j, s) in self.slots.iter().enumerate().skip(i) {
            self.index.insert(s.kind, j);
        }
        self.dim -= d;
        Some(removed)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn offsets_follow_insertion_and_removal() {
        let mut l = Layout::new(2);
        assert_eq!(l.vehicle_offset(1), Some(VEHICLE_DIM));
        assert_eq!(l.vehicle_offset(2), None);
        let a = l.push(SlotKind::Feature(7));
        let p = l.push(SlotKind::Pose(1));
        let b = l.push(SlotKind::Feature(3));
        assert_eq!(a, 2 * VEHICLE_DIM);
        assert_eq!(p, a + FEATURE_DIM);
        assert_eq!(b, p + POSE_DIM);
        assert_eq!(l.dim(), b + FEATURE_DIM);
        let removed = l.remove(SlotKind::Pose(1)).unwrap();
        assert_eq!(removed.offset, p);
        assert_eq!(l.feature_offset(3), Some(p));
        assert_eq!(l.features().collect::<Vec<_>>(), vec![(7, a), (3, p)]);
        assert_eq!(l.dim(), 2 * VEHICLE_DIM + 2 * FEATURE_DIM);
        assert!(l.remove(SlotKind::Vehicle(0)).is_none());
    }

    #[test]
    fn poses_last_moves_features_in_front_of_poses() {
        let mut l = Layout::new(1);
        let v = VEHICLE_DIM;
        l.push(SlotKind::Feature(1));
        assert_eq!(l.poses_last(), None);
        l.push(SlotKind::Pose(10));
        l.push(SlotKind::Pose(11));
        assert_eq!(l.poses_last(), None);
        l.push(SlotKind::Feature(2));
        let (start, order) = l.poses_last().unwrap();
        // Old layout: f1 [v, v+3), p10 [v+3, v+9), p11 [v+9, v+15), f2 [v+15, v+18).
        assert_eq!(start, v + 3);
        let expect: Vec<usize> = (v + 15..v + 18).chain(v + 3..v + 15).collect();
        assert_eq!(order, expect);
        assert_eq!(l.feature_offset(2), Some(v + 3));
        assert_eq!(l.pose_offset(10), Some(v + 6));
        assert_eq!(l.pose_offset(11), Some(v + 12));
        assert_eq!(
            l.poses().map(|(id, _)| id).collect::<Vec<_>>(),
            vec![10, 11]
        );
        assert_eq!(l.poses_last(), None);
        assert_eq!(l.dim(), v + 18);
    }
}
