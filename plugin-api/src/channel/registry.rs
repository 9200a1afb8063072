//! [`TopicRegistry`]: what is registered by topic while the process initializes, looked up
//! per message once it runs.

use std::collections::HashMap;
use std::sync::{Mutex, OnceLock};

type ByTopic<V> = HashMap<Box<[u8]>, Vec<V>, foldhash::fast::RandomState>;

/// Entries by topic (a publisher's registered types, a backend's publishers), registered
/// while modules initialize and read once per message when they run.
///
/// Registration goes through a lock. The first [`get`](Self::get) seals the registry:
/// from then on a lookup takes no lock and no reference count, and a registration is
/// refused ([`register`](Self::register) returns `None`). Call `get` only from the phase
/// where registering has ended (AimRT's: publishing starts once every module has
/// initialized); [`peek`](Self::peek) reads without sealing. Topics are looked up by
/// their bytes, so a lookup does not check the topic as UTF-8 again.
///
/// ```
/// use aimrt_plugin_api::channel::TopicRegistry;
///
/// let registry = TopicRegistry::default();
/// assert_eq!(registry.register("/chatter", |types| types.push("pb:Note")), Some(()));
/// // The first lookup seals it; a lookup is by the topic's bytes.
/// assert_eq!(registry.get(b"/chatter"), &["pb:Note"]);
/// assert!(registry.get(b"/other").is_empty());
/// assert_eq!(registry.register("/late", |types| types.push("pb:Note")), None);
/// ```
pub struct TopicRegistry<V> {
    open: Mutex<ByTopic<V>>,
    sealed: OnceLock<Sealed<V>>,
}

/// Up to how many topics a sealed registry is a list, scanned by each topic's length and
/// bytes: cheaper than hashing the topic for the few topics a process mostly has.
const FEW: usize = 8;

/// A sealed registry: a short list, or a hash map beyond [`FEW`] topics.
enum Sealed<V> {
    Few(Vec<(Box<[u8]>, Vec<V>)>),
    Many(ByTopic<V>),
}

impl<V> Sealed<V> {
    fn of(map: ByTopic<V>) -> Sealed<V> {
        if map.len() <= FEW {
            Sealed::Few(map.into_iter().collect())
        } else {
            Sealed::Many(map)
        }
    }

    #[inline]
    fn get(&self, topic: &[u8]) -> &[V] {
        match self {
            Sealed::Few(list) => list
                .iter()
                .find(|(t, _)| **t == *topic)
                .map_or(&[], |(_, v)| v.as_slice()),
            Sealed::Many(map) => map.get(topic).map_or(&[], Vec::as_slice),
        }
    }

    fn for_each(&self, f: impl FnMut(&V)) {
        match self {
            Sealed::Few(list) => list.iter().flat_map(|(_, v)| v).for_each(f),
            Sealed::Many(map) => map.values().flatten().for_each(f),
        }
    }
}

impl<V> Default for TopicRegistry<V> {
    fn default() -> Self {
        TopicRegistry {
            open: Mutex::default(),
            sealed: OnceLock::new(),
        }
    }
}

impl<V> TopicRegistry<V> {
    /// Runs `add` on the entries of `topic` (created empty) while the registry is open;
    /// `None` once it is sealed (nothing runs).
    pub fn register<R>(&self, topic: &str, add: impl FnOnce(&mut Vec<V>) -> R) -> Option<R> {
        let mut open = self.open.lock().unwrap_or_else(|e| e.into_inner());
        // Checked under the lock that sealing holds while it takes the map: nothing
        // registered here can be left out of the sealed map.
        if self.sealed.get().is_some() {
            return None;
        }
        let entries = open.entry(topic.as_bytes().into()).or_default();
        Some(add(entries))
    }

    /// The entries of `topic` (empty when none), sealing the registry on the first call.
    pub fn get(&self, topic: &[u8]) -> &[V] {
        let sealed = match self.sealed.get() {
            Some(sealed) => sealed,
            None => self.seal(),
        };
        sealed.get(topic)
    }

    /// Runs `f` on the entries of `topic` without sealing the registry (under the lock
    /// while it is open).
    pub fn peek<R>(&self, topic: &[u8], f: impl FnOnce(&[V]) -> R) -> R {
        if let Some(sealed) = self.sealed.get() {
            return f(sealed.get(topic));
        }
        let open = self.open.lock().unwrap_or_else(|e| e.into_inner());
        match self.sealed.get() {
            Some(sealed) => f(sealed.get(topic)),
            None => f(open.get(topic).map_or(&[], Vec::as_slice)),
        }
    }

    /// Runs `f` on every entry of every topic without sealing the registry (under the
    /// lock while it is open): a backend's shutdown, releasing what it registered.
    ///
    /// ```
    /// use aimrt_plugin_api::channel::TopicRegistry;
    ///
    /// let registry = TopicRegistry::default();
    /// registry.register("/a", |types| types.extend([1, 2]));
    /// registry.register("/b", |types| types.push(3));
    /// let mut sum = 0;
    /// registry.for_each(|n| sum += n);
    /// assert_eq!(sum, 6);
    /// assert!(!registry.is_sealed());
    /// ```
    pub fn for_each(&self, f: impl FnMut(&V)) {
        if let Some(sealed) = self.sealed.get() {
            return sealed.for_each(f);
        }
        let open = self.open.lock().unwrap_or_else(|e| e.into_inner());
        match self.sealed.get() {
            Some(sealed) => sealed.for_each(f),
            None => open.values().flatten().for_each(f),
        }
    }

    /// Whether the first [`get`](Self::get) has sealed it.
    pub fn is_sealed(&self) -> bool {
        self.sealed.get().is_some()
    }

    #[cold]
    fn seal(&self) -> &Sealed<V> {
        let mut open = self.open.lock().unwrap_or_else(|e| e.into_inner());
        self.sealed
            .get_or_init(|| Sealed::of(std::mem::take(&mut *open)))
    }
}

impl<V> std::fmt::Debug for TopicRegistry<V> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TopicRegistry")
            .field("sealed", &self.is_sealed())
            .finish_non_exhaustive()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Arc;

    /// Sealed as a list (up to `FEW` topics) or as a map (more), a registry finds every
    /// topic by its bytes, tells topics that differ in their last byte or their length
    /// apart, and visits every entry.
    #[test]
    fn a_sealed_registry_of_few_or_many_topics_finds_each() {
        for topics in [1, FEW, FEW + 1, 40] {
            let r = TopicRegistry::default();
            for i in 0..topics {
                r.register(&format!("/topic{i}"), |v| v.push(i));
            }
            for i in 0..topics {
                assert_eq!(
                    r.get(format!("/topic{i}").as_bytes()),
                    [i],
                    "{topics} topics"
                );
            }
            assert!(r.get(b"/topic").is_empty());
            assert!(r.get(format!("/topic{topics}").as_bytes()).is_empty());
            assert!(r.get(b"").is_empty());
            let mut sum = 0;
            r.for_each(|i| sum += i);
            assert_eq!(sum, (0..topics).sum::<usize>());
            r.peek(b"/topic0", |v| assert_eq!(v, [0]));
        }
    }

    #[test]
    fn for_each_visits_every_entry_open_and_sealed() {
        let r = TopicRegistry::default();
        r.register("/a", |v| v.extend([1, 2]));
        r.register("/b", |v| v.push(4));
        let all = |r: &TopicRegistry<i32>| {
            let mut seen = Vec::new();
            r.for_each(|n| seen.push(*n));
            seen.sort_unstable();
            seen
        };
        assert_eq!(all(&r), [1, 2, 4]);
        assert!(!r.is_sealed(), "for_each must not seal");
        assert_eq!(r.get(b"/b"), &[4]);
        assert_eq!(all(&r), [1, 2, 4]);
    }

    #[test]
    fn a_registration_is_seen_until_sealed_and_refused_after() {
        let r = TopicRegistry::default();
        assert_eq!(r.register("/a", |v| v.push(1)), Some(()));
        assert_eq!(r.register("/a", |v| v.push(2)), Some(()));
        assert_eq!(r.peek(b"/a", <[i32]>::to_vec), vec![1, 2]);
        assert!(!r.is_sealed(), "peek must not seal");
        assert_eq!(r.get(b"/a"), &[1, 2]);
        assert!(r.is_sealed());
        assert_eq!(r.register("/a", |v| v.push(3)), None);
        assert_eq!(r.register("/b", |v| v.push(4)), None);
        assert_eq!(r.get(b"/a"), &[1, 2]);
        assert!(r.get(b"/b").is_empty());
        assert_eq!(r.peek(b"/a", <[i32]>::len), 2);
        // Not UTF-8: simply not found.
        assert!(r.get(&[0xff, 0xfe]).is_empty());
    }

    #[test]
    fn every_registration_that_returned_some_is_in_the_sealed_map() {
        // Registrations race the seal: each one that was accepted must be found after.
        for _ in 0..50 {
            let r = Arc::new(TopicRegistry::default());
            let writers: Vec<_> = (0..4)
                .map(|t| {
                    let r = r.clone();
                    std::thread::spawn(move || {
                        (0..200)
                            .filter(|i| r.register(&format!("/t{t}"), |v| v.push(*i)).is_some())
                            .count()
                    })
                })
                .collect();
            let sealed_len = r.get(b"/t0").len();
            let accepted: Vec<usize> = writers.into_iter().map(|w| w.join().unwrap()).collect();
            for (t, n) in accepted.iter().enumerate() {
                assert_eq!(r.get(format!("/t{t}").as_bytes()).len(), *n);
            }
            assert!(sealed_len <= accepted[0]);
        }
    }
}
