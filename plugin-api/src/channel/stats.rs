//! Per-topic counters: what was published, delivered, and dropped and why.

use std::fmt;

/// Why a message was not delivered. Every drop is counted per topic; the first of each
/// kind per topic is also logged (never silently lost, never a log flood).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum DropReason {
    /// The topic matches no `pub_topics_options` rule, so no backend carries it.
    NoRoute,
    /// No subscriber of the topic and type exists (in this process, for backends that can
    /// tell).
    NoSubscriber,
    /// Published before `start` or after the channel shut down.
    WrongPhase,
    /// The publisher did not register the type for the topic in `initialize`.
    Unregistered,
    /// The message could not be encoded in the context's format.
    Format,
    /// The subscriber executor refused the delivery (queue full, shut down).
    Refused,
    /// The subscriber's library could not decode the bytes.
    DecodeFailed,
    /// The subscriber callback panicked (or failed).
    SubscriberFailed,
    /// A reason a newer backend reported that this runtime does not know.
    Other,
    /// A channel filter held the message back, or failed (ABI 1.7).
    Filtered,
    /// A backend took the message in `publish` and could not send it afterwards: a send
    /// error, a peer's error answer or none, or still queued when it shut down (ABI 1.8).
    /// On a subscriber's side: messages a transport shows were published and never
    /// arrived (zenoh: a gap in the publisher's sequence, ABI 1.12).
    Lost,
}

impl DropReason {
    /// Every reason, in code order.
    pub const ALL: [DropReason; 11] = [
        DropReason::NoRoute,
        DropReason::NoSubscriber,
        DropReason::WrongPhase,
        DropReason::Unregistered,
        DropReason::Format,
        DropReason::Refused,
        DropReason::DecodeFailed,
        DropReason::SubscriberFailed,
        DropReason::Other,
        DropReason::Filtered,
        DropReason::Lost,
    ];

    /// The code that crosses the ABI.
    pub fn code(self) -> u32 {
        self as u32
    }

    /// The reason of a code (unknown codes read as [`DropReason::Other`]).
    pub fn from_code(code: u32) -> DropReason {
        DropReason::ALL
            .get(code as usize)
            .copied()
            .unwrap_or(DropReason::Other)
    }

    /// A short name for reports: `no route`, `no subscriber`, …
    pub fn name(self) -> &'static str {
        match self {
            DropReason::NoRoute => "no route",
            DropReason::NoSubscriber => "no subscriber",
            DropReason::WrongPhase => "wrong phase",
            DropReason::Unregistered => "unregistered type",
            DropReason::Format => "format",
            DropReason::Refused => "executor refused",
            DropReason::DecodeFailed => "decode failed",
            DropReason::SubscriberFailed => "subscriber failed",
            DropReason::Other => "other",
            DropReason::Filtered => "filtered",
            DropReason::Lost => "lost after publish",
        }
    }
}

impl fmt::Display for DropReason {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// The counters of one topic, summed over its message types and modules.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct TopicStats {
    /// Messages accepted by `publish`.
    pub published: u64,
    /// Subscriber callbacks that ran to completion (one message to two subscribers counts
    /// two).
    pub delivered: u64,
    /// Messages (or deliveries) dropped, per reason; reasons with a zero count are left out.
    pub dropped: Vec<(DropReason, u64)>,
}

impl TopicStats {
    /// The count of one reason.
    pub fn dropped_for(&self, reason: DropReason) -> u64 {
        self.dropped
            .iter()
            .find(|(r, _)| *r == reason)
            .map_or(0, |(_, n)| *n)
    }

    /// All drops.
    pub fn dropped_total(&self) -> u64 {
        self.dropped.iter().map(|(_, n)| n).sum()
    }
}

impl fmt::Display for TopicStats {
    /// `published 10, delivered 20, dropped 1 (no subscriber: 1)`.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "published {}, delivered {}, dropped {}",
            self.published,
            self.delivered,
            self.dropped_total()
        )?;
        if !self.dropped.is_empty() {
            let parts: Vec<String> = self
                .dropped
                .iter()
                .map(|(r, n)| format!("{r}: {n}"))
                .collect();
            write!(f, " ({})", parts.join(", "))?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn codes_round_trip_and_unknown_codes_are_other() {
        for r in DropReason::ALL {
            assert_eq!(DropReason::from_code(r.code()), r);
        }
        assert_eq!(DropReason::from_code(999), DropReason::Other);
        let s = TopicStats {
            published: 3,
            delivered: 2,
            dropped: vec![(DropReason::NoSubscriber, 1)],
        };
        assert_eq!(
            s.to_string(),
            "published 3, delivered 2, dropped 1 (no subscriber: 1)"
        );
        assert_eq!(s.dropped_for(DropReason::NoSubscriber), 1);
        assert_eq!(s.dropped_for(DropReason::Format), 0);
    }
}
