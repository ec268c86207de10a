//! The vehicle process's fusion thread: the vehicle's [`VehicleFusion`] (DDF node and the
//! batch of received information) runs here, so that channel bookkeeping, fusing received
//! deltas into the EKF and forming the next deltas never hold up the estimator thread's IMU
//! processing.
//!
//! The estimator thread keeps the links (iceoryx2 ports stay on the thread that opened them)
//! and forwards what they deliver as [`Job`]s; for a round it hands the fusion thread its
//! filter ([`VehicleEstimator::lend`](crate::agent::VehicleEstimator::lend)) and keeps
//! predicting the vehicle's part of it; the fusion thread fuses the batch into the filter,
//! forms the map information and the deltas, and hands it back ([`Done::Round`]), and the
//! estimator applies the IMU samples of the meantime to it again
//! ([`VehicleEstimator::give_back`](crate::agent::VehicleEstimator::give_back)).
//! Messages for the links come back as [`Done`] too, with the DDF's counters and channel views
//! for the reports. They are encoded here ([`WireOutgoing`]); a round's are handed over one by
//! one as each is formed ([`Done::Send`]), so that the estimator thread sends one while the
//! next channel forms its delta: a vehicle with three neighbours held three dense k × k deltas
//! at once until the round's end otherwise (the wire form of one is about half of it).

use std::sync::mpsc::{Receiver, Sender, channel};
use std::thread::JoinHandle;

use canopy_fusion::ddf::{ChannelView, DdfMessage, NodeStats, Outgoing};
use canopy_fusion::keys::Merge;
use canopy_fusion::slam::SlamFilter;
use canopy_fusion::topology::NodeId;

use crate::agent::{FusionCounters, VehicleFusion};
use crate::wire::{Compression, WireOutgoing};

/// Work for the fusion thread.
#[derive(Debug)]
pub enum Job {
    /// A DDF message from a neighbour.
    Message {
        /// Simulation time of receipt [s].
        now: f64,
        /// Sender.
        from: NodeId,
        /// The message (boxed: deltas are large, link events small).
        msg: Box<DdfMessage>,
    },
    /// A message from a neighbour as received, decoded here when the thread takes it (the
    /// wire form is about half the dense one; see `Vehicle::service_links`). Other kinds than
    /// DDF messages are skipped; a body that fails to decode is counted by its link.
    Received {
        /// Simulation time of receipt [s].
        now: f64,
        /// Sender.
        from: NodeId,
        /// The message.
        msg: canopy_transport::Received,
    },
    /// The link to `peer` came up.
    LinkUp {
        /// Simulation time [s].
        now: f64,
        /// The neighbour.
        peer: NodeId,
    },
    /// The link to `peer` went down.
    LinkDown {
        /// The neighbour.
        peer: NodeId,
    },
    /// A fusion round on the filter handed over.
    Round {
        /// Round time [s].
        now: f64,
        /// The filter.
        filter: Box<SlamFilter>,
        /// Submap budgets of the capacity-limited links for this round
        /// ([`crate::radio::capacity_budgets`]).
        budgets: Vec<(NodeId, usize)>,
        /// Data sharing: this vehicle's records since the last round (empty otherwise).
        records: Vec<canopy_fusion::share::Item>,
    },
}

/// The DDF's counters and channels after a job (for the estimator thread's reports).
#[derive(Clone, Debug, Default)]
pub struct FusionView {
    /// Counters of the fusion half.
    pub counters: FusionCounters,
    /// Every channel of the DDF node.
    pub channels: Vec<ChannelView>,
    /// Failures of the fusion half by reason ([`VehicleFusion::rejections`]).
    pub rejections: std::collections::BTreeMap<String, u64>,
    /// The DDF node's counters.
    pub node: NodeStats,
    /// The correspondences the DDF node has adopted.
    pub merges: Vec<Merge>,
    /// Whose own frame the filter is in after the job (own frames; `None`: shared frame).
    pub frame_owner: Option<NodeId>,
    /// This vehicle's side of the team frame (own frames).
    pub alignment: Option<crate::frames::AlignmentReport>,
}

impl FusionView {
    fn of(f: &VehicleFusion) -> Self {
        Self {
            counters: f.counters(),
            channels: f.ddf().map(|d| d.channels().collect()).unwrap_or_default(),
            rejections: f.rejections().counts.clone(),
            node: f.ddf().map(|d| d.stats()).unwrap_or_default(),
            merges: f.merges(),
            frame_owner: f.frame_owner(),
            alignment: f.team_frame().map(crate::frames::TeamFrame::report),
        }
    }

    /// The channel to `peer`.
    pub fn channel(&self, peer: NodeId) -> Option<ChannelView> {
        self.channels.iter().find(|c| c.peer == peer).copied()
    }
}

/// What the fusion thread finished.
#[derive(Debug)]
pub enum Done {
    /// A message or link event handled: replies to send at `now`.
    Replies {
        /// Time of the job [s].
        now: f64,
        /// Messages to send, encoded.
        out: Vec<WireOutgoing>,
        /// Counters and channels now.
        view: FusionView,
    },
    /// A message of the round in progress, encoded as soon as it was formed and handed over
    /// at once, so that the estimator thread sends it (and drops its bytes) while the next
    /// channel forms its delta.
    Send {
        /// Round time [s].
        now: f64,
        /// The message.
        out: WireOutgoing,
    },
    /// A round done: the fused filter and the round's messages.
    Round {
        /// Round time [s].
        now: f64,
        /// The filter, fused (its messages went ahead as [`Done::Send`]).
        filter: Box<SlamFilter>,
        /// Data sharing: the other vehicles' frames the round processed, for the monitor's
        /// audit.
        remote: Vec<crate::sharing::RemoteFrame>,
        /// Counters and channels now.
        view: FusionView,
    },
}

/// The messages to send after a call into the fusion half, encoded. An error it returns it
/// has already counted by reason and logged once with its cause (`VehicleFusion::reject`,
/// visible in `checks.json`), and the refused input changed nothing, so there is nothing to
/// send.
fn replies(
    r: Result<Vec<Outgoing>, crate::agent::AgentError>,
    compression: Compression,
) -> Vec<WireOutgoing> {
    r.unwrap_or_else(|_counted| Vec::new())
        .into_iter()
        .map(|o| WireOutgoing::encode(&o, compression))
        .collect()
}

/// The estimator thread's handle on the fusion thread.
#[derive(Debug)]
pub struct FusionThread {
    jobs: Option<Sender<Job>>,
    done: Receiver<Done>,
    handle: Option<JoinHandle<()>>,
}

impl FusionThread {
    /// Starts the thread with the vehicle's fusion half; messages are encoded with
    /// `compression` (`[fusion] delta_compression`).
    pub fn spawn(mut fusion: VehicleFusion, compression: Compression) -> std::io::Result<Self> {
        let (jobs, job_rx) = channel::<Job>();
        let (done_tx, done) = channel::<Done>();
        let handle = std::thread::Builder::new()
            .name("fusion".into())
            .spawn(move || {
                for job in job_rx {
                    let msg = match job {
                        Job::Message { now, from, msg } => Done::Replies {
                            now,
                            out: replies(fusion.on_message(now, from, *msg), compression),
                            view: FusionView::of(&fusion),
                        },
                        Job::Received { now, from, msg } => Done::Replies {
                            now,
                            out: match crate::wire::decode_ddf(&msg) {
                                Some(Ok(m)) => {
                                    drop(msg);
                                    replies(fusion.on_message(now, from, m), compression)
                                }
                                // Not a DDF message, or one that failed to decode (counted by
                                // its link, `rejected.body`).
                                _ => Vec::new(),
                            },
                            view: FusionView::of(&fusion),
                        },
                        Job::LinkUp { now, peer } => Done::Replies {
                            now,
                            out: replies(fusion.on_link_up(now, peer), compression),
                            view: FusionView::of(&fusion),
                        },
                        Job::LinkDown { peer } => {
                            // Refused (an unknown peer): counted by the fusion half.
                            let _counted = fusion.on_link_down(peer);
                            Done::Replies {
                                now: f64::NAN,
                                out: Vec::new(),
                                view: FusionView::of(&fusion),
                            }
                        }
                        Job::Round {
                            now,
                            mut filter,
                            budgets,
                            records,
                        } => {
                            // A refused budget is counted by reason by the fusion half.
                            let _counted = fusion.set_link_budgets(&budgets);
                            fusion.publish_own(records);
                            // Each message encoded as it is formed (module docs). Messages
                            // formed before a refusal are booked and go out; the refusal is
                            // counted by reason by the fusion half.
                            let _counted = fusion.round_each(&mut filter, now, &mut |o| {
                                let out = WireOutgoing::encode(&o, compression);
                                drop(o);
                                // An error: the estimator thread is gone, and with it the
                                // links (the loop ends at the round's own `Done`).
                                let _gone = done_tx.send(Done::Send { now, out });
                            });
                            Done::Round {
                                now,
                                filter,
                                remote: fusion.take_remote_frames(),
                                view: FusionView::of(&fusion),
                            }
                        }
                    };
                    let round = match &msg {
                        Done::Round { filter, .. } => Some(filter.num_features()),
                        Done::Replies { .. } | Done::Send { .. } => None,
                    };
                    if done_tx.send(msg).is_err() {
                        break;
                    }
                    // The heap's idle high-water mark back to the kernel (after the round is
                    // handed back, so the estimator does not wait for it).
                    if let Some(features) = round {
                        canopy_fusion::runtime::trim_heap(canopy_fusion::runtime::heap_slack(
                            features,
                        ));
                    }
                }
            })?;
        Ok(Self {
            jobs: Some(jobs),
            done,
            handle: Some(handle),
        })
    }

    /// Queues a job (a no-op once the thread has ended).
    pub fn submit(&self, job: Job) {
        if let Some(j) = &self.jobs {
            let _ = j.send(job);
        }
    }

    /// A finished job, if one is waiting.
    pub fn try_done(&self) -> Option<Done> {
        self.done.try_recv().ok()
    }

    /// The next finished job, waiting for it (`None` if the thread has ended).
    pub fn wait_done(&self) -> Option<Done> {
        self.done.recv().ok()
    }
}

impl Drop for FusionThread {
    fn drop(&mut self) {
        // Closing the job channel ends the thread's loop.
        self.jobs.take();
        if let Some(h) = self.handle.take() {
            let _ = h.join();
        }
    }
}
