//! zenoh access control for canopy's key layout, and the count of what it refuses.
//!
//! canopy's zenoh links ([`crate::net`]) publish data `a → b` on `{prefix}/link/{a}/{b}` and
//! declare the liveliness token `{prefix}/alive/{a}/{b}`; `b` subscribes to the first and watches
//! `{prefix}/alive/{a}/{b}` from its side. A [`ZenohAccess`] lists, per authenticated user
//! (zenoh `auth_usrpwd` user names: one per node), the directed links `from → to` it may carry,
//! and becomes zenoh's `access_control` block: **default deny** in both flows, so a session (or a
//! router) refuses every publication, subscription, liveliness token or liveliness subscription
//! of a peer on keys that are not its own side of one of its links, and sends each peer only its
//! own links' traffic (egress rules, the mirror image). A non-neighbour
//! — or a neighbour forging another node's key — is refused by zenoh before the message reaches
//! any subscriber.
//!
//! zenoh refuses silently: its access-control interceptor only emits a `trace` event per refused
//! message (`"… is unauthorized to Put (ingress) on KEY"`). [`refusal_counter`] is a
//! `tracing` layer, filtered to that one target, that counts those events by action and key
//! ([`refusals`]); a process installs it next to its log output. The parse depends on zenoh's
//! wording (zenoh 1.10); `transport/tests/access.rs` fails if it changes.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::sync::Mutex;

use tracing_subscriber::Layer;
use tracing_subscriber::filter::{LevelFilter, Targets};

use crate::envelope::NodeId;

/// A zenoh access-control message type (zenoh's `AclMessage`, the ones canopy's links use).
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum AclMessage {
    /// Publication.
    Put,
    /// Subscriber declaration.
    DeclareSubscriber,
    /// Liveliness token declaration.
    LivelinessToken,
    /// Liveliness subscriber declaration.
    DeclareLivelinessSubscriber,
    /// Liveliness query (a liveliness subscriber's history).
    LivelinessQuery,
    /// Reply to a (liveliness) query.
    Reply,
}

/// The direction a zenoh access-control rule applies to, seen from the enforcing node.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum AclFlow {
    /// Messages the node receives from the user's session.
    Ingress,
    /// Messages the node sends to the user's session.
    Egress,
}

impl AclFlow {
    fn zenoh_name(self) -> &'static str {
        match self {
            AclFlow::Ingress => "ingress",
            AclFlow::Egress => "egress",
        }
    }
}

impl AclMessage {
    fn zenoh_name(self) -> &'static str {
        match self {
            AclMessage::Put => "put",
            AclMessage::DeclareSubscriber => "declare_subscriber",
            AclMessage::LivelinessToken => "liveliness_token",
            AclMessage::DeclareLivelinessSubscriber => "declare_liveliness_subscriber",
            AclMessage::LivelinessQuery => "liveliness_query",
            AclMessage::Reply => "reply",
        }
    }
}

/// One permission: the enforcing node may receive from (ingress) or send to (egress) `user`
/// `message` on these keys.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct AclGrant {
    /// The authenticated user (zenoh `auth_usrpwd` user name).
    pub user: String,
    /// Which direction.
    pub flow: AclFlow,
    /// What it may do.
    pub message: AclMessage,
    /// On which keys (zenoh key expressions).
    pub keys: Vec<String>,
}

/// The access-control rules of one zenoh node (a session or a router): default deny, plus
/// [`AclGrant`]s.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct ZenohAccess {
    /// Everything allowed; all else is refused.
    pub grants: Vec<AclGrant>,
    /// Key expressions (`{prefix}/link/**` of each key prefix served) whose subscriber
    /// declarations every accepted user is told of (egress), so that a publication it is not
    /// allowed to make is sent and refused here — counted — rather than silently never routed.
    pub announce: Vec<String>,
}

/// A directed link of canopy's layout that a user may carry: `from → to`, `from` being the
/// user's own node.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct AclLink {
    /// The user that runs node `from`.
    pub user: String,
    /// Its node.
    pub from: NodeId,
    /// The node it talks to.
    pub to: NodeId,
}

impl ZenohAccess {
    /// Rules for canopy's link layout under `key_prefix`, enforced at node `to` of every
    /// `from → to` link towards the user of `from`:
    /// - ingress (what `from` may send here): publish on `link/from/to`, subscribe to
    ///   `link/to/from`, declare the token `alive/from/to`, watch (subscribe to, query)
    ///   `alive/to/from`, reply with `alive/from/to`;
    /// - egress (what this node may send to `from`): the mirror image — publish on
    ///   `link/to/from`, subscribe to `link/from/to`, token `alive/to/from`, watch
    ///   `alive/from/to`, reply with `alive/to/from`. zenoh's `default_permission = "deny"`
    ///   covers both flows, so without these the node could not even declare its own side.
    ///
    /// At a peer session `to`, pass the links of its neighbours towards it; at a router, every
    /// directed link of the run (both directions of each).
    pub fn for_links(key_prefix: &str, links: &[AclLink]) -> Self {
        let mut by_user: BTreeMap<(String, AclFlow, AclMessage), Vec<String>> = BTreeMap::new();
        for l in links {
            for (flow, a, b) in [
                (AclFlow::Ingress, l.from, l.to),
                (AclFlow::Egress, l.to, l.from),
            ] {
                // `a` is the sending side of the data key `link/a/b` in this flow.
                for (message, key) in [
                    (AclMessage::Put, format!("{key_prefix}/link/{a}/{b}")),
                    (
                        AclMessage::DeclareSubscriber,
                        format!("{key_prefix}/link/{b}/{a}"),
                    ),
                    (
                        AclMessage::LivelinessToken,
                        format!("{key_prefix}/alive/{a}/{b}"),
                    ),
                    (
                        AclMessage::DeclareLivelinessSubscriber,
                        format!("{key_prefix}/alive/{b}/{a}"),
                    ),
                    (
                        AclMessage::LivelinessQuery,
                        format!("{key_prefix}/alive/{b}/{a}"),
                    ),
                    (AclMessage::Reply, format!("{key_prefix}/alive/{a}/{b}")),
                ] {
                    let keys = by_user.entry((l.user.clone(), flow, message)).or_default();
                    if !keys.contains(&key) {
                        keys.push(key);
                    }
                }
            }
        }
        Self {
            announce: vec![format!("{key_prefix}/link/**")],
            grants: by_user
                .into_iter()
                .map(|((user, flow, message), keys)| AclGrant {
                    user,
                    flow,
                    message,
                    keys,
                })
                .collect(),
        }
    }

    /// The rules of `self` and `other` together: a router serving several key prefixes (the
    /// fusion links and the control plane of a run) enforces both sets.
    pub fn merge(mut self, other: ZenohAccess) -> Self {
        self.grants.extend(other.grants);
        for a in other.announce {
            if !self.announce.contains(&a) {
                self.announce.push(a);
            }
        }
        self
    }

    /// zenoh's `access_control` configuration block (JSON5) for a node that accepts the users
    /// `accepted` (each gets a subject, so that zenoh traces every decision about it — a user
    /// matching no subject is refused without a trace — and the announcement rule).
    pub(crate) fn to_json5(&self, accepted: &[&str]) -> String {
        let mut users: Vec<&str> = self.grants.iter().map(|g| g.user.as_str()).collect();
        users.extend_from_slice(accepted);
        users.sort_unstable();
        users.dedup();
        let announce = "announce".to_string();
        let mut rules = vec![format!(
            "{{id: {}, messages: [\"declare_subscriber\"], flows: [\"egress\"], \
             permission: \"allow\", key_exprs: {}}}",
            json_str(&announce),
            json_list(&self.announce)
        )];
        let mut policies: Vec<Vec<String>> = vec![vec![announce]; users.len()];
        for (i, g) in self.grants.iter().enumerate() {
            let id = format!("r{i}");
            rules.push(format!(
                "{{id: {}, messages: [{}], flows: [{}], permission: \"allow\", key_exprs: {}}}",
                json_str(&id),
                json_str(g.message.zenoh_name()),
                json_str(g.flow.zenoh_name()),
                json_list(&g.keys)
            ));
            if let Some(s) = users.iter().position(|x| *x == g.user) {
                policies[s].push(id);
            }
        }
        let subjects: Vec<String> = users
            .iter()
            .enumerate()
            .map(|(i, u)| format!("{{id: \"s{i}\", usernames: [{}]}}", json_str(u)))
            .collect();
        let policies: Vec<String> = policies
            .iter()
            .enumerate()
            .map(|(s, rules)| format!("{{rules: {}, subjects: [\"s{s}\"]}}", json_list(rules)))
            .collect();
        format!(
            "{{enabled: true, default_permission: \"deny\", rules: [{}], subjects: [{}], \
             policies: [{}]}}",
            rules.join(","),
            subjects.join(","),
            policies.join(",")
        )
    }
}

pub(crate) fn json_str(s: &str) -> String {
    let mut out = String::with_capacity(s.len() + 2);
    out.push('"');
    for c in s.chars() {
        match c {
            '"' => out.push_str("\\\""),
            '\\' => out.push_str("\\\\"),
            c if (c as u32) < 0x20 => {
                let _ = write!(out, "\\u{:04x}", c as u32);
            }
            c => out.push(c),
        }
    }
    out.push('"');
    out
}

pub(crate) fn json_list(v: &[String]) -> String {
    format!(
        "[{}]",
        v.iter().map(|s| json_str(s)).collect::<Vec<_>>().join(",")
    )
}

/// zenoh's access-control interceptor: the `tracing` target of its decisions.
const ACL_TARGET: &str = "zenoh::net::routing::interceptor::access_control";
/// How many actions zenoh evaluates when it caches the permissions of a key expression
/// (`compute_keyexpr_cache`: query, reply, put, delete, subscriber, queryable, token, liveliness
/// query, liveliness subscriber).
const CACHED_ACTIONS: usize = 9;

/// Refusals counted in this process, by `"<action> on <key>"`.
static REFUSALS: Mutex<BTreeMap<String, u64>> = Mutex::new(BTreeMap::new());

fn refusal_map() -> std::sync::MutexGuard<'static, BTreeMap<String, u64>> {
    // A panic while counting cannot leave the map half-updated (one `+= 1`).
    REFUSALS.lock().unwrap_or_else(|p| p.into_inner())
}

/// What zenoh's access control has refused in this process so far (sessions and routers alike),
/// by `"<action> on <key>"`, e.g. `"Put (ingress) on canopy/run/link/8/2"`: messages refused,
/// not the permissions zenoh evaluates ahead when it caches a key. Empty unless
/// [`refusal_counter`] is installed.
pub fn refusals() -> BTreeMap<String, u64> {
    refusal_map().clone()
}

/// Total of [`refusals`].
pub fn refused_total() -> u64 {
    refusals().values().sum()
}

/// A `tracing` layer that counts zenoh access-control refusals ([`refusals`]); it sees only
/// zenoh's access-control target (its own filter), so it adds nothing to other logging.
pub fn refusal_counter<S>() -> impl Layer<S>
where
    S: tracing::Subscriber + for<'a> tracing_subscriber::registry::LookupSpan<'a>,
{
    RefusalCounter.with_filter(Targets::new().with_target(ACL_TARGET, LevelFilter::TRACE))
}

struct RefusalCounter;

/// Reads the `message` field of an event.
#[derive(Default)]
struct Message(String);

impl tracing::field::Visit for Message {
    fn record_debug(&mut self, field: &tracing::field::Field, value: &dyn std::fmt::Debug) {
        if field.name() == "message" {
            let _ = write!(self.0, "{value:?}");
        }
    }
}

thread_local! {
    /// The permission cache zenoh is computing on this thread, if any.
    static CACHING: std::cell::RefCell<Classifier> = std::cell::RefCell::new(Classifier::default());
}

impl<S: tracing::Subscriber> Layer<S> for RefusalCounter {
    fn on_event(
        &self,
        event: &tracing::Event<'_>,
        _ctx: tracing_subscriber::layer::Context<'_, S>,
    ) {
        let mut m = Message::default();
        event.record(&mut m);
        if let Some(what) = CACHING.with(|c| c.borrow_mut().refusal(&m.0)) {
            *refusal_map().entry(what).or_insert(0) += 1;
        }
    }
}

/// Tells zenoh's decisions on messages from the evaluations it makes while caching a key's
/// permissions. zenoh traces both alike (`"… is (un)authorized to ACTION on KEY"`); a cache
/// computation opens with `"ACL (…): caching permissions for `KEY` ..."` and then evaluates each
/// of [`CACHED_ACTIONS`] actions once on the same thread (one event each, since every user has
/// exactly one subject — [`ZenohAccess::to_json5`]). A decision on a cached key is traced as
/// `"Using cached result: …"`.
#[derive(Default, Debug)]
struct Classifier {
    /// The key being cached and the actions already evaluated for it.
    caching: Option<(String, Vec<String>)>,
}

impl Classifier {
    /// `Some("<action> on <key>")` when `message` is a refused message.
    fn refusal(&mut self, message: &str) -> Option<String> {
        if let Some(rest) = message.split_once("caching permissions for `") {
            let key = rest.1.split('`').next().unwrap_or_default();
            self.caching = Some((key.to_string(), Vec::new()));
            return None;
        }
        let (refused, what) = if let Some((_, w)) = message.split_once(" is unauthorized to ") {
            (true, w.trim())
        } else if let Some((_, w)) = message.split_once(" is authorized to ") {
            (false, w.trim())
        } else {
            return None;
        };
        if !message.starts_with("Using cached result:")
            && let Some((action, key)) = what.rsplit_once(" on ")
            && let Some((caching, seen)) = self.caching.as_mut()
            && caching == key
            && !seen.iter().any(|a| a == action)
        {
            seen.push(action.to_string());
            if seen.len() == CACHED_ACTIONS {
                self.caching = None;
            }
            return None;
        }
        self.caching = None;
        refused.then(|| what.to_string())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn refusals_of_messages_are_counted_and_cache_evaluations_are_not() {
        let mut c = Classifier::default();
        // A decision on a cached key, refused and allowed.
        assert_eq!(
            c.refusal("Using cached result: abc is unauthorized to Put (ingress) on k/1")
                .as_deref(),
            Some("Put (ingress) on k/1")
        );
        assert_eq!(
            c.refusal("Using cached result: abc is authorized to Put (ingress) on k/1"),
            None
        );
        // A cache computation: nine evaluations, none counted, then a decision on an uncached
        // message of the same key is counted.
        assert_eq!(
            c.refusal("ACL (ingress): caching permissions for `k/2` ..."),
            None
        );
        let actions = [
            "Query (ingress)",
            "Reply (ingress)",
            "Put (ingress)",
            "Delete (ingress)",
            "Declare/Undeclare Subscriber (ingress)",
            "Declare/Undeclare Queryable (ingress)",
            "Declare/Undeclare Liveliness Token (ingress)",
            "Liveliness Query (ingress)",
            "Declare Liveliness Subscriber (ingress)",
        ];
        assert_eq!(actions.len(), CACHED_ACTIONS);
        for a in actions {
            assert_eq!(
                c.refusal(&format!("abc on usr(uav8) is unauthorized to {a} on k/2")),
                None,
                "{a}"
            );
        }
        assert_eq!(
            c.refusal("abc on usr(uav8) is unauthorized to Put (ingress) on k/2")
                .as_deref(),
            Some("Put (ingress) on k/2")
        );
        // An action repeated during a computation is a message decision.
        c.refusal("ACL (egress): caching permissions for `k/3` ...");
        c.refusal("abc on usr(uav8) is unauthorized to Put (egress) on k/3");
        assert_eq!(
            c.refusal("abc on usr(uav8) is unauthorized to Put (egress) on k/3")
                .as_deref(),
            Some("Put (egress) on k/3")
        );
        assert_eq!(c.refusal("something else"), None);
    }

    #[test]
    fn grants_cover_both_sides_of_a_link() {
        let a = ZenohAccess::for_links(
            "p",
            &[AclLink {
                user: "uav3".into(),
                from: 3,
                to: 2,
            }],
        );
        let egress = |m: AclMessage| {
            a.grants
                .iter()
                .find(|g| g.message == m && g.user == "uav3" && g.flow == AclFlow::Egress)
                .map(|g| g.keys.clone())
                .unwrap_or_default()
        };
        // What node 2 may send to uav3: the mirror image.
        assert_eq!(egress(AclMessage::Put), vec!["p/link/2/3".to_string()]);
        assert_eq!(
            egress(AclMessage::LivelinessToken),
            vec!["p/alive/2/3".to_string()]
        );
        let keys = |m: AclMessage| {
            a.grants
                .iter()
                .find(|g| g.message == m && g.user == "uav3" && g.flow == AclFlow::Ingress)
                .map(|g| g.keys.clone())
                .unwrap_or_default()
        };
        assert_eq!(keys(AclMessage::Put), vec!["p/link/3/2".to_string()]);
        assert_eq!(
            keys(AclMessage::DeclareSubscriber),
            vec!["p/link/2/3".to_string()]
        );
        assert_eq!(
            keys(AclMessage::LivelinessToken),
            vec!["p/alive/3/2".to_string()]
        );
        assert_eq!(
            keys(AclMessage::DeclareLivelinessSubscriber),
            vec!["p/alive/2/3".to_string()]
        );
        let json = a.to_json5(&["uav3", "uav9"]);
        assert!(json.contains("default_permission: \"deny\""));
        assert!(json.contains("usernames: [\"uav3\"]"));
        assert!(json.contains("usernames: [\"uav9\"]"));
    }
}
