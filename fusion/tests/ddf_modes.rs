//! Fusion modes: central (hub) against decentralized on the same data, the erratum of eq.
//! 21.92 (a vehicle's own information must not come back to it through the hub), isolated
//! mode, and mode/topology validation.

mod common;

use canopy_fusion::ddf::{DdfConfig, DdfError, DdfNode, Mode};
use canopy_fusion::info::MapInformation;
use canopy_fusion::topology::{NodeId, Topology, TopologyError};
use common::{Shape, Sim, features, origin, random_observations, tree};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Relative equality of two runs of the same data (different summation orders: ~1e-15).
const EQ_TOL: f64 = 1e-9;

/// The same observations, made over several rounds by 6 vehicles, fused (a) decentralized on a
/// random tree of the vehicles and (b) through a hub (star; the hub observes nothing): every
/// vehicle ends with the same map information in both modes (= the centralized sum), and the
/// hub's estimate is that sum too.
#[test]
fn central_mode_reaches_the_same_map_information_as_decentralized() {
    let mut rng = ChaCha8Rng::seed_from_u64(31);
    for _case in 0..10 {
        let vehicles: Vec<NodeId> = (1..=6).map(NodeId).collect();
        let hub = NodeId(0);
        let dec_topo = {
            let t = tree(Shape::Random, 6, &mut rng);
            // Relabel the random tree's nodes onto the vehicle ids.
            let map: std::collections::BTreeMap<NodeId, NodeId> = t
                .nodes()
                .iter()
                .copied()
                .zip(vehicles.iter().copied())
                .collect();
            Topology::tree(
                vehicles.clone(),
                t.links().iter().map(|(a, b)| (map[a], map[b])),
            )
            .unwrap()
        };
        let star = Topology::star(hub, vehicles.clone()).unwrap();
        let feats = features(8, &mut rng);
        // Observation schedule: (round, vehicle, information).
        let mut schedule: Vec<(u64, NodeId, MapInformation)> = Vec::new();
        for r in 0..4 {
            for &v in &vehicles {
                if rng.random_bool(0.6) {
                    schedule.push((r, v, random_observations(&feats, &mut rng, true)));
                }
            }
        }
        let mut dec = Sim::new(
            dec_topo,
            Mode::Decentralized,
            DdfConfig::default(),
            rng.random(),
        );
        let mut cen = Sim::new(
            star,
            Mode::Central { hub },
            DdfConfig::default(),
            rng.random(),
        );
        dec.handshake(5);
        cen.handshake(5);
        for r in 0..20 {
            for (_, v, obs) in schedule.iter().filter(|(t, _, _)| *t == r) {
                dec.observe(*v, obs);
                cen.observe(*v, obs);
            }
            dec.round();
            cen.round();
        }
        let central = dec.all_ever.clone();
        assert!(cen.all_ever.relative_difference(&central).unwrap() < 1e-12);
        for &v in &vehicles {
            let a = &dec.nodes[&v].estimate;
            let b = &cen.nodes[&v].estimate;
            assert!(a.relative_difference(b).unwrap() <= EQ_TOL, "vehicle {v}");
            assert!(
                b.relative_difference(&central).unwrap() <= EQ_TOL,
                "vehicle {v}"
            );
        }
        assert!(
            cen.nodes[&hub]
                .estimate
                .relative_difference(&central)
                .unwrap()
                <= EQ_TOL
        );
        assert!(cen.nodes[&hub].own.is_empty(), "the hub observes nothing");
    }
}

/// Erratum of eq. 21.92: adding the whole central increment to the vehicle's estimate
/// (as printed) counts the vehicle's own information twice. With channel filters on the
/// vehicle–hub links, vehicle 1 ends with Y_1 + Y_2 exactly; the literal eq. 21.92, computed
/// here independently, gives 2·Y_1 + Y_2, which exceeds the centralized information.
#[test]
fn a_vehicles_own_information_is_not_counted_twice_through_the_hub() {
    let mut rng = ChaCha8Rng::seed_from_u64(32);
    let feats = features(4, &mut rng);
    let (hub, v1, v2) = (NodeId(0), NodeId(1), NodeId(2));
    let mut sim = Sim::new(
        Topology::star(hub, [v1, v2]).unwrap(),
        Mode::Central { hub },
        DdfConfig::default(),
        5,
    );
    sim.handshake(5);
    let y1 = random_observations(&feats, &mut rng, true);
    let y2 = random_observations(&feats, &mut rng, true);
    sim.observe(v1, &y1);
    sim.observe(v2, &y2);
    for _ in 0..4 {
        sim.round();
    }
    let central = y1.add(&y2).unwrap();
    let ours = &sim.nodes[&v1].estimate;
    assert!(ours.relative_difference(&central).unwrap() <= EQ_TOL);
    // λ_max(Y_1 − Y_central) ≤ 0 up to round-off (1e-12 relative).
    assert!(ours.psd_excess_over(&central).unwrap() <= 1e-12 * central.matrix_norm_max());
    // Literal eq. 21.92: Y_local(k) += Y_central(k) − Y_central(k−1), with Y_central(k−1) = 0
    // and Y_central(k) = Y_1 + Y_2 (eq. 21.88).
    let literal = y1.add(&central).unwrap();
    let excess = literal.psd_excess_over(&central).unwrap();
    assert!(
        excess > 0.1 * y1.max_eigenvalue().unwrap(),
        "literal 21.92 over-counts by {excess}"
    );
    // Ours differs from the literal by exactly Y_1.
    assert!(literal.sub(ours).unwrap().relative_difference(&y1).unwrap() <= EQ_TOL);
}

/// Isolated mode: no channels, no messages, every vehicle keeps only its own information.
#[test]
fn isolated_mode_does_not_fuse() {
    let mut rng = ChaCha8Rng::seed_from_u64(33);
    let topo = tree(Shape::Random, 4, &mut rng);
    let ids: Vec<NodeId> = topo.nodes().to_vec();
    let feats = features(5, &mut rng);
    let mut sim = Sim::new(topo, Mode::Isolated, DdfConfig::default(), 6);
    sim.link_all_up();
    for &id in &ids {
        let obs = random_observations(&feats, &mut rng, false);
        sim.observe(id, &obs);
    }
    for _ in 0..5 {
        sim.round();
    }
    assert_eq!(sim.delivered, 0);
    for n in sim.nodes.values() {
        assert_eq!(n.ddf.neighbours().count(), 0);
        assert_eq!(n.estimate.relative_difference(&n.own).unwrap(), 0.0);
    }
}

/// Channel-filter modes refuse topologies they cannot fuse on exactly.
#[test]
fn modes_validate_their_topology() {
    let n = |i| NodeId(i);
    let cyclic = Topology::new(
        [n(1), n(2), n(3), n(4)],
        [(n(1), n(2)), (n(2), n(3)), (n(3), n(4)), (n(4), n(2))],
    )
    .unwrap();
    let err = DdfNode::for_mode(
        Mode::Decentralized,
        n(1),
        1,
        &cyclic,
        origin(),
        DdfConfig::default(),
    )
    .unwrap_err();
    assert_eq!(
        err,
        DdfError::Topology(TopologyError::Cycle(vec![n(2), n(3), n(4)]))
    );
    assert!(err.to_string().contains("2 -> 3 -> 4 -> 2"), "{err}");
    let chain = Topology::chain([n(0), n(1), n(2)]).unwrap();
    assert!(matches!(
        DdfNode::for_mode(
            Mode::Central { hub: n(0) },
            n(1),
            1,
            &chain,
            origin(),
            DdfConfig::default()
        ),
        Err(DdfError::Topology(TopologyError::NotAStar { .. }))
    ));
    assert!(matches!(
        DdfNode::for_mode(
            Mode::Decentralized,
            n(9),
            1,
            &chain,
            origin(),
            DdfConfig::default()
        ),
        Err(DdfError::Topology(TopologyError::UnknownNode { .. }))
    ));
    // Isolated mode needs no particular topology.
    assert!(
        DdfNode::for_mode(
            Mode::Isolated,
            n(1),
            1,
            &cyclic,
            origin(),
            DdfConfig::default()
        )
        .is_ok()
    );
}
