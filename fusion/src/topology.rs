//! Fusion-network topology: nodes (vehicles, hub), undirected links, and validation.
//!
//! Channel filters (design.md §4) are exact only on a tree: with a cycle the same information
//! reaches a node by two paths and is counted twice. [`Topology::tree`] therefore rejects a
//! cycle (naming its nodes in order), an unknown node, a self-link, a duplicate link and a
//! disconnected node with a typed [`TopologyError`].

use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, BTreeSet, VecDeque};

/// Identifier of a fusion node (a vehicle process or the central hub).
#[derive(
    Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize, Default,
)]
#[serde(transparent)]
pub struct NodeId(pub u32);

impl std::fmt::Display for NodeId {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}", self.0)
    }
}

/// Why a topology is invalid.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum TopologyError {
    /// No node at all.
    #[error("topology has no nodes")]
    Empty,
    /// A node is listed twice.
    #[error("node {0} is listed twice")]
    DuplicateNode(NodeId),
    /// A link names a node that is not in the node list.
    #[error("link {a} - {b} names unknown node {node}")]
    UnknownNode {
        /// The unknown node.
        node: NodeId,
        /// One end of the link.
        a: NodeId,
        /// The other end.
        b: NodeId,
    },
    /// A link from a node to itself.
    #[error("self-link at node {0}")]
    SelfLink(NodeId),
    /// The same undirected link twice.
    #[error("duplicate link {0} - {1}")]
    DuplicateLink(NodeId, NodeId),
    /// A cycle; channel filters would count information twice around it.
    #[error("cycle in a channel-filter topology (channel filters need a tree): {}", fmt_cycle(.0))]
    Cycle(Vec<NodeId>),
    /// Nodes not reachable from the first node.
    #[error("disconnected: node(s) {} not reachable from node {from}", fmt_list(.nodes))]
    Disconnected {
        /// The node the search started from (the first listed node).
        from: NodeId,
        /// The unreachable nodes.
        nodes: Vec<NodeId>,
    },
    /// Central mode needs a star: every link joins the hub to a vehicle.
    #[error("central mode needs a star around hub {hub}, but link {a} - {b} does not touch it")]
    NotAStar {
        /// The hub.
        hub: NodeId,
        /// One end of the offending link.
        a: NodeId,
        /// The other end.
        b: NodeId,
    },
}

fn fmt_list(nodes: &[NodeId]) -> String {
    nodes
        .iter()
        .map(|n| n.to_string())
        .collect::<Vec<_>>()
        .join(", ")
}

fn fmt_cycle(nodes: &[NodeId]) -> String {
    let mut s = nodes
        .iter()
        .map(|n| n.to_string())
        .collect::<Vec<_>>()
        .join(" -> ");
    if let Some(first) = nodes.first() {
        s.push_str(&format!(" -> {first}"));
    }
    s
}

/// An undirected graph of fusion nodes. Construction checks the node list and the links
/// (unknown node, self-link, duplicate link); [`require_tree`](Self::require_tree) adds the
/// channel-filter requirement (no cycle, connected).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Topology {
    nodes: Vec<NodeId>,
    links: Vec<(NodeId, NodeId)>,
    adjacency: BTreeMap<NodeId, Vec<NodeId>>,
}

impl Topology {
    /// A graph from a node list and undirected links (each given once, in either orientation).
    pub fn new(
        nodes: impl IntoIterator<Item = NodeId>,
        links: impl IntoIterator<Item = (NodeId, NodeId)>,
    ) -> Result<Self, TopologyError> {
        let nodes: Vec<NodeId> = nodes.into_iter().collect();
        if nodes.is_empty() {
            return Err(TopologyError::Empty);
        }
        let mut adjacency: BTreeMap<NodeId, Vec<NodeId>> = BTreeMap::new();
        for &n in &nodes {
            if adjacency.insert(n, Vec::new()).is_some() {
                return Err(TopologyError::DuplicateNode(n));
            }
        }
        let mut seen = BTreeSet::new();
        let mut kept = Vec::new();
        for (a, b) in links {
            for node in [a, b] {
                if !adjacency.contains_key(&node) {
                    return Err(TopologyError::UnknownNode { node, a, b });
                }
            }
            if a == b {
                return Err(TopologyError::SelfLink(a));
            }
            if !seen.insert((a.min(b), a.max(b))) {
                return Err(TopologyError::DuplicateLink(a, b));
            }
            adjacency.get_mut(&a).expect("checked above").push(b);
            adjacency.get_mut(&b).expect("checked above").push(a);
            kept.push((a, b));
        }
        Ok(Self {
            nodes,
            links: kept,
            adjacency,
        })
    }

    /// A graph that must be a tree (connected, acyclic): what channel-filter modes need.
    pub fn tree(
        nodes: impl IntoIterator<Item = NodeId>,
        links: impl IntoIterator<Item = (NodeId, NodeId)>,
    ) -> Result<Self, TopologyError> {
        let t = Self::new(nodes, links)?;
        t.require_tree()?;
        Ok(t)
    }

    /// The star of central mode: `hub` linked to every vehicle.
    pub fn star(
        hub: NodeId,
        vehicles: impl IntoIterator<Item = NodeId>,
    ) -> Result<Self, TopologyError> {
        let vehicles: Vec<NodeId> = vehicles.into_iter().collect();
        let links: Vec<_> = vehicles.iter().map(|&v| (hub, v)).collect();
        Self::tree(std::iter::once(hub).chain(vehicles), links)
    }

    /// A chain n_0 − n_1 − … in the given order.
    pub fn chain(nodes: impl IntoIterator<Item = NodeId>) -> Result<Self, TopologyError> {
        let nodes: Vec<NodeId> = nodes.into_iter().collect();
        let links: Vec<_> = nodes.windows(2).map(|w| (w[0], w[1])).collect();
        Self::tree(nodes, links)
    }

    /// Checks that the graph is a star centred on `hub` (central mode).
    pub fn require_star(&self, hub: NodeId) -> Result<(), TopologyError> {
        self.require_tree()?;
        if !self.contains(hub) {
            return Err(TopologyError::UnknownNode {
                node: hub,
                a: hub,
                b: hub,
            });
        }
        for &(a, b) in &self.links {
            if a != hub && b != hub {
                return Err(TopologyError::NotAStar { hub, a, b });
            }
        }
        Ok(())
    }

    /// Channel-filter requirement: no cycle ([`TopologyError::Cycle`] lists the nodes on the
    /// first cycle found, in order along it) and connected ([`TopologyError::Disconnected`]
    /// names the nodes unreachable from the first listed node).
    pub fn require_tree(&self) -> Result<(), TopologyError> {
        if let Some(cycle) = self.find_cycle() {
            return Err(TopologyError::Cycle(cycle));
        }
        let reach = self.bfs_distances(self.nodes[0]);
        let missing: Vec<NodeId> = self
            .nodes
            .iter()
            .copied()
            .filter(|n| !reach.contains_key(n))
            .collect();
        if !missing.is_empty() {
            return Err(TopologyError::Disconnected {
                from: self.nodes[0],
                nodes: missing,
            });
        }
        Ok(())
    }

    /// True for a connected acyclic graph.
    pub fn is_tree(&self) -> bool {
        self.require_tree().is_ok()
    }

    /// Nodes in the order given.
    pub fn nodes(&self) -> &[NodeId] {
        &self.nodes
    }

    /// Links in the order given.
    pub fn links(&self) -> &[(NodeId, NodeId)] {
        &self.links
    }

    /// True if `node` is in the graph.
    pub fn contains(&self, node: NodeId) -> bool {
        self.adjacency.contains_key(&node)
    }

    /// Neighbours of a node in link order (`None` for an unknown node).
    pub fn neighbours(&self, node: NodeId) -> Option<&[NodeId]> {
        self.adjacency.get(&node).map(Vec::as_slice)
    }

    /// A shortest path from `from` to `to`, both included (`None` if unknown or unreachable).
    pub fn path(&self, from: NodeId, to: NodeId) -> Option<Vec<NodeId>> {
        if !self.contains(from) || !self.contains(to) {
            return None;
        }
        let mut parent: BTreeMap<NodeId, NodeId> = BTreeMap::new();
        let mut queue = VecDeque::from([from]);
        parent.insert(from, from);
        while let Some(n) = queue.pop_front() {
            if n == to {
                let mut path = vec![to];
                let mut cur = to;
                while cur != from {
                    cur = parent[&cur];
                    path.push(cur);
                }
                path.reverse();
                return Some(path);
            }
            for &m in &self.adjacency[&n] {
                if let std::collections::btree_map::Entry::Vacant(e) = parent.entry(m) {
                    e.insert(n);
                    queue.push_back(m);
                }
            }
        }
        None
    }

    /// Diameter in hops (longest shortest path); `None` when disconnected. On a tree with
    /// perfect links, information crosses the network in this many fusion rounds.
    pub fn diameter(&self) -> Option<usize> {
        let mut best = 0;
        for &n in &self.nodes {
            let d = self.bfs_distances(n);
            if d.len() != self.nodes.len() {
                return None;
            }
            best = best.max(d.values().copied().max().unwrap_or(0));
        }
        Some(best)
    }

    fn bfs_distances(&self, from: NodeId) -> BTreeMap<NodeId, usize> {
        let mut dist = BTreeMap::from([(from, 0)]);
        let mut queue = VecDeque::from([from]);
        while let Some(n) = queue.pop_front() {
            let d = dist[&n];
            for &m in &self.adjacency[&n] {
                if let std::collections::btree_map::Entry::Vacant(e) = dist.entry(m) {
                    e.insert(d + 1);
                    queue.push_back(m);
                }
            }
        }
        dist
    }

    /// The first cycle met by an iterative depth-first search, as the nodes along it.
    fn find_cycle(&self) -> Option<Vec<NodeId>> {
        let mut parent: BTreeMap<NodeId, NodeId> = BTreeMap::new();
        for &root in &self.nodes {
            if parent.contains_key(&root) {
                continue;
            }
            parent.insert(root, root);
            // Stack of (node, next neighbour index to look at).
            let mut stack = vec![(root, 0usize)];
            let mut on_stack = BTreeSet::from([root]);
            while let Some(&mut (n, ref mut next)) = stack.last_mut() {
                let nbrs = &self.adjacency[&n];
                if *next >= nbrs.len() {
                    on_stack.remove(&n);
                    stack.pop();
                    continue;
                }
                let m = nbrs[*next];
                *next += 1;
                if m == parent[&n] {
                    // The tree edge back to the parent (links are unique, so only once).
                    continue;
                }
                if on_stack.contains(&m) {
                    // Back edge n → ancestor m: the cycle is m → … → n along parents.
                    let mut cycle = vec![n];
                    let mut cur = n;
                    while cur != m {
                        cur = parent[&cur];
                        cycle.push(cur);
                    }
                    cycle.reverse();
                    return Some(cycle);
                }
                if let std::collections::btree_map::Entry::Vacant(e) = parent.entry(m) {
                    e.insert(n);
                    on_stack.insert(m);
                    stack.push((m, 0));
                }
            }
        }
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ids(v: &[u32]) -> Vec<NodeId> {
        v.iter().map(|&i| NodeId(i)).collect()
    }

    fn links(v: &[(u32, u32)]) -> Vec<(NodeId, NodeId)> {
        v.iter().map(|&(a, b)| (NodeId(a), NodeId(b))).collect()
    }

    #[test]
    fn cycle_is_rejected_naming_its_nodes_in_order() {
        // A tree 1-2, 2-3, 3-4, 4-5 plus the closing link 5-2: the cycle is 2 → 3 → 4 → 5 → 2.
        let err = Topology::tree(
            ids(&[1, 2, 3, 4, 5]),
            links(&[(1, 2), (2, 3), (3, 4), (4, 5), (5, 2)]),
        )
        .unwrap_err();
        let TopologyError::Cycle(cycle) = &err else {
            panic!("expected a cycle, got {err:?}")
        };
        // The cycle is reported along its links, from some node on it; check it is exactly the
        // cycle {2, 3, 4, 5} walked along existing links.
        assert_eq!(cycle.len(), 4);
        let mut sorted = cycle.clone();
        sorted.sort();
        assert_eq!(sorted, ids(&[2, 3, 4, 5]));
        let t = Topology::new(
            ids(&[1, 2, 3, 4, 5]),
            links(&[(1, 2), (2, 3), (3, 4), (4, 5), (5, 2)]),
        )
        .unwrap();
        for k in 0..cycle.len() {
            let (a, b) = (cycle[k], cycle[(k + 1) % cycle.len()]);
            assert!(
                t.neighbours(a).unwrap().contains(&b),
                "{a} - {b} is not a link"
            );
        }
        let msg = err.to_string();
        assert!(msg.contains("cycle"), "{msg}");
        let expected = format!(
            "{} -> {} -> {} -> {} -> {}",
            cycle[0], cycle[1], cycle[2], cycle[3], cycle[0]
        );
        assert!(msg.contains(&expected), "{msg}");
        // The simplest case: a triangle, reported in DFS order 1 → 2 → 3 → 1.
        let tri = Topology::tree(ids(&[1, 2, 3]), links(&[(1, 2), (2, 3), (3, 1)])).unwrap_err();
        assert_eq!(tri, TopologyError::Cycle(ids(&[1, 2, 3])));
        assert!(tri.to_string().contains("1 -> 2 -> 3 -> 1"), "{tri}");
    }

    #[test]
    fn structural_errors_name_the_offending_nodes() {
        assert_eq!(
            Topology::new(ids(&[]), links(&[])).unwrap_err(),
            TopologyError::Empty
        );
        assert_eq!(
            Topology::new(ids(&[1, 2, 1]), links(&[])).unwrap_err(),
            TopologyError::DuplicateNode(NodeId(1))
        );
        assert_eq!(
            Topology::new(ids(&[1, 2]), links(&[(1, 9)])).unwrap_err(),
            TopologyError::UnknownNode {
                node: NodeId(9),
                a: NodeId(1),
                b: NodeId(9)
            }
        );
        assert_eq!(
            Topology::new(ids(&[1, 2]), links(&[(2, 2)])).unwrap_err(),
            TopologyError::SelfLink(NodeId(2))
        );
        assert_eq!(
            Topology::new(ids(&[1, 2]), links(&[(1, 2), (2, 1)])).unwrap_err(),
            TopologyError::DuplicateLink(NodeId(2), NodeId(1))
        );
        let err = Topology::tree(ids(&[1, 2, 3, 4]), links(&[(1, 2), (3, 4)])).unwrap_err();
        assert_eq!(
            err,
            TopologyError::Disconnected {
                from: NodeId(1),
                nodes: ids(&[3, 4])
            }
        );
        assert!(err.to_string().contains("3, 4"), "{err}");
        let chain = Topology::chain(ids(&[1, 2, 3])).unwrap();
        assert_eq!(chain.require_star(NodeId(2)), Ok(()));
        assert_eq!(
            chain.require_star(NodeId(1)),
            Err(TopologyError::NotAStar {
                hub: NodeId(1),
                a: NodeId(2),
                b: NodeId(3)
            })
        );
    }

    #[test]
    fn diameter_paths_and_neighbours() {
        // 1 - 2 - 3 - 4 with a branch 2 - 5 - 6: longest path 6-5-2-3-4 (4 hops).
        let t = Topology::tree(
            ids(&[1, 2, 3, 4, 5, 6]),
            links(&[(1, 2), (2, 3), (3, 4), (2, 5), (5, 6)]),
        )
        .unwrap();
        assert_eq!(t.diameter(), Some(4));
        assert_eq!(t.path(NodeId(6), NodeId(4)), Some(ids(&[6, 5, 2, 3, 4])));
        assert_eq!(t.path(NodeId(1), NodeId(1)), Some(ids(&[1])));
        assert_eq!(t.path(NodeId(1), NodeId(99)), None);
        assert_eq!(t.neighbours(NodeId(2)), Some(ids(&[1, 3, 5]).as_slice()));
        assert_eq!(t.neighbours(NodeId(7)), None);
        assert_eq!(
            Topology::star(NodeId(0), ids(&[1, 2, 3]))
                .unwrap()
                .diameter(),
            Some(2)
        );
        assert_eq!(Topology::chain(ids(&[7])).unwrap().diameter(), Some(0));
        let split = Topology::new(ids(&[1, 2]), links(&[])).unwrap();
        assert_eq!(split.diameter(), None);
        assert!(!split.is_tree());
    }
}
