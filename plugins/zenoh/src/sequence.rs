//! Messages lost on the way, seen by a subscriber as gaps in a publisher's sequence.
//!
//! Each channel message this plugin puts carries zenoh's source info: the publisher's
//! global id and a sequence number that goes up by one with each put zenoh took
//! ([`crate::channel`]). zenoh's `put` does not say when it drops a message (a congested
//! link under `Drop`, a link that closed, a message over the receiver's
//! `max_message_size`); the subscriber sees the sequence jump and counts the difference.
//! Messages without source info (a C++ AimRT publisher's) are not counted.

use zenoh::session::ZenohId;

/// A publisher: its session's id and its entity id in that session.
pub(crate) type Source = (ZenohId, u32);

/// The sources one subscriber keeps, at most; the one heard from longest ago makes room.
/// A source heard again after that starts afresh (nothing counted for its first message).
pub(crate) const MAX_SOURCES: usize = 64;

/// A message this far or less behind the one expected is a late or repeated one (no
/// gap); further behind, the publisher started its sequence again (a process restarted
/// with the same zenoh id).
const LATE: u32 = 1024;

/// The next sequence number expected of each publisher of one key, the most recently
/// heard first.
#[derive(Debug, Default)]
pub(crate) struct Sequences {
    expected: Vec<(Source, u32)>,
}

impl Sequences {
    /// How many messages of `source` were skipped right before `sn`: 0 for the next one,
    /// the first one heard from a source, or a late one.
    pub(crate) fn missed(&mut self, source: Source, sn: u32) -> u32 {
        let Some(i) = self.expected.iter().position(|(s, _)| *s == source) else {
            if self.expected.len() == MAX_SOURCES {
                self.expected.pop();
            }
            self.expected.insert(0, (source, sn.wrapping_add(1)));
            return 0;
        };
        self.expected[..=i].rotate_right(1);
        let expected = &mut self.expected[0].1;
        let ahead = sn.wrapping_sub(*expected);
        let behind = expected.wrapping_sub(sn);
        if behind != 0 && behind <= LATE {
            return 0;
        }
        *expected = sn.wrapping_add(1);
        if ahead < 1 << 31 {
            ahead
        } else {
            0
        }
    }
}

#[cfg(test)]
mod tests {
    use std::str::FromStr;

    use super::*;

    /// A distinct source per `n`.
    fn source(n: u32) -> Source {
        (ZenohId::from_str("1f").expect("a zenoh id"), n)
    }

    fn gaps(seq: &mut Sequences, heard: &[(u32, u32)]) -> Vec<u32> {
        heard
            .iter()
            .map(|&(s, sn)| seq.missed(source(s), sn))
            .collect()
    }

    #[test]
    fn the_first_message_of_a_source_starts_it_and_a_jump_is_the_count_skipped() {
        let mut seq = Sequences::default();
        assert_eq!(
            gaps(
                &mut seq,
                &[(0, 7), (0, 8), (0, 9), (0, 12), (0, 13), (0, 20)]
            ),
            [0, 0, 0, 2, 0, 6]
        );
    }

    #[test]
    fn sources_are_counted_apart_and_a_wrap_is_no_gap() {
        let mut seq = Sequences::default();
        assert_eq!(
            gaps(
                &mut seq,
                &[
                    (0, u32::MAX - 1),
                    (1, 0),
                    (0, u32::MAX),
                    (1, 1),
                    (0, 0),
                    (1, 3),
                    (0, 2)
                ]
            ),
            [0, 0, 0, 0, 0, 1, 1]
        );
    }

    #[test]
    fn a_late_or_repeated_message_is_no_gap_and_a_restart_begins_again() {
        let mut seq = Sequences::default();
        assert_eq!(
            gaps(
                &mut seq,
                &[(0, 5000), (0, 5003), (0, 5001), (0, 5003), (0, 5004)]
            ),
            [0, 2, 0, 0, 0]
        );
        // Far behind: the publisher began again; its next message follows on.
        assert_eq!(gaps(&mut seq, &[(0, 0), (0, 1), (0, 3)]), [0, 0, 1]);
    }

    #[test]
    fn the_source_heard_from_longest_ago_makes_room_and_starts_afresh() {
        let mut seq = Sequences::default();
        for s in 0..MAX_SOURCES as u32 {
            assert_eq!(seq.missed(source(s), 10), 0);
        }
        // Source 0 heard again: now the newest; 1 is the oldest.
        assert_eq!(seq.missed(source(0), 12), 1);
        assert_eq!(seq.missed(source(MAX_SOURCES as u32), 10), 0);
        assert_eq!(seq.expected.len(), MAX_SOURCES);
        // 1 made room: heard again, it starts afresh; 0 was kept.
        assert_eq!(seq.missed(source(1), 15), 0);
        assert_eq!(seq.missed(source(0), 14), 1);
    }
}
