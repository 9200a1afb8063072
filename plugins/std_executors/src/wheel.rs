//! A hierarchical timing wheel over abstract ticks: the pure core of `time_wheel`, with
//! no clock and no threads, so its tick logic is tested deterministically.
//!
//! # Model
//!
//! Tick `k` is the boundary `start + k·dt`. An item scheduled for tick `T` comes out of
//! [`Wheel::advance`] in the call that moves `current` to `T` or past it — never before.
//! `current` is the last tick processed; scheduling for a tick `≤ current` is refused
//! (the caller runs the item now).
//!
//! Level `i` has `sizes[i]` slots, each covering `span(i) = sizes[0]·…·sizes[i-1]` ticks
//! (`span(0) = 1`). An item goes to the lowest level whose horizon holds it:
//! `T/span(i) − current/span(i) < sizes[i]`, in slot `(T/span(i)) % sizes[i]`. Because the
//! level below did not hold it, its bucket is strictly ahead of `current`'s bucket, so a
//! slot never mixes two laps. Items beyond the top level wait in an ordered overflow map.
//! When `current` enters a new bucket of level `i ≥ 1`, that bucket's slot is emptied and
//! its items are placed again (they land strictly lower, or are due); this *cascade* runs
//! from the top level down, then level 0's slot for `current` fires. This is AimRT's design
//! with its index bugs (B1–B5 of the spec) fixed: every delay, at every level and beyond,
//! fires on exactly its tick.
//!
//! [`Wheel::next_event`] gives the next tick where anything happens (a fire or a cascade),
//! so an idle driver sleeps until then and `advance` jumps over empty ticks.

use std::collections::BTreeMap;

/// The wheel; `T` is the scheduled item (a task in `time_wheel`).
#[derive(Debug)]
pub(crate) struct Wheel<T> {
    sizes: Vec<u64>,
    spans: Vec<u64>,
    levels: Vec<Vec<Vec<(u64, T)>>>,
    overflow: BTreeMap<u64, Vec<T>>,
    current: u64,
    len: usize,
}

impl<T> Wheel<T> {
    /// A wheel with the given level sizes (each ≥ 1, at least one level), at tick 0.
    pub(crate) fn new(sizes: &[u64]) -> Wheel<T> {
        assert!(
            !sizes.is_empty() && sizes.iter().all(|&s| s > 0),
            "wheel sizes are validated by the caller"
        );
        let mut spans = Vec::with_capacity(sizes.len());
        let mut span = 1u64;
        for &s in sizes {
            spans.push(span);
            span = span.saturating_mul(s);
        }
        Wheel {
            sizes: sizes.to_vec(),
            spans,
            levels: sizes
                .iter()
                .map(|&s| (0..s).map(|_| Vec::new()).collect())
                .collect(),
            overflow: BTreeMap::new(),
            current: 0,
            len: 0,
        }
    }

    /// The last tick processed.
    pub(crate) fn current(&self) -> u64 {
        self.current
    }

    /// Items scheduled.
    #[cfg(test)]
    pub(crate) fn len(&self) -> usize {
        self.len
    }

    /// Schedules `item` for tick `target`; `Err(item)` if that tick is already processed.
    pub(crate) fn insert(&mut self, target: u64, item: T) -> Result<(), T> {
        if target <= self.current {
            return Err(item);
        }
        self.len += 1;
        self.place(target, item);
        Ok(())
    }

    fn place(&mut self, target: u64, item: T) {
        for (i, (&size, &span)) in self.sizes.iter().zip(&self.spans).enumerate() {
            if target / span - self.current / span < size {
                let slot = ((target / span) % size) as usize;
                self.levels[i][slot].push((target, item));
                return;
            }
        }
        self.overflow.entry(target).or_default().push(item);
    }

    /// Moves `current` to `to` (if ahead), appending every item that comes due, in tick
    /// order, to `out`.
    pub(crate) fn advance(&mut self, to: u64, out: &mut Vec<T>) {
        while self.current < to {
            match self.next_event() {
                Some(tick) if tick <= to => {
                    self.current = tick - 1;
                    self.step(out);
                }
                _ => self.current = to,
            }
        }
    }

    /// One tick forward: overflow, cascades from the top, then level 0's slot fires.
    fn step(&mut self, out: &mut Vec<T>) {
        self.current += 1;
        let now = self.current;
        let top = self.sizes.len() - 1;
        if now % self.spans[top] == 0 {
            let (size, span) = (self.sizes[top], self.spans[top]);
            while let Some(entry) = self.overflow.first_entry() {
                if *entry.key() / span >= now / span + size {
                    break;
                }
                let (target, items) = entry.remove_entry();
                for item in items {
                    self.replace_or_fire(target, item, out);
                }
            }
        }
        for i in (1..self.sizes.len()).rev() {
            let span = self.spans[i];
            if now % span == 0 {
                let slot = ((now / span) % self.sizes[i]) as usize;
                for (target, item) in std::mem::take(&mut self.levels[i][slot]) {
                    self.replace_or_fire(target, item, out);
                }
            }
        }
        let slot = (now % self.sizes[0]) as usize;
        for (target, item) in std::mem::take(&mut self.levels[0][slot]) {
            debug_assert_eq!(target, now, "level 0 holds only this lap's items");
            self.len -= 1;
            out.push(item);
        }
    }

    fn replace_or_fire(&mut self, target: u64, item: T, out: &mut Vec<T>) {
        if target <= self.current {
            self.len -= 1;
            out.push(item);
        } else {
            self.place(target, item);
        }
    }

    /// Removes every scheduled item (for shutdown), in no particular order.
    pub(crate) fn drain(&mut self) -> Vec<T> {
        let mut all = Vec::with_capacity(self.len);
        for level in &mut self.levels {
            for slot in level.iter_mut() {
                all.extend(slot.drain(..).map(|(_, item)| item));
            }
        }
        for (_, items) in std::mem::take(&mut self.overflow) {
            all.extend(items);
        }
        self.len = 0;
        all
    }

    /// The next tick at which an item fires or moves down a level; `None` when empty.
    pub(crate) fn next_event(&self) -> Option<u64> {
        if self.len == 0 {
            return None;
        }
        let c = self.current;
        let mut best: Option<u64> = None;
        let mut consider = |t: u64| best = Some(best.map_or(t, |b| b.min(t)));
        for (i, (&size, &span)) in self.sizes.iter().zip(&self.spans).enumerate() {
            let bucket = c / span;
            for d in 1..size {
                let b = bucket + d;
                if !self.levels[i][(b % size) as usize].is_empty() {
                    // Level 0 fires at its tick; higher levels cascade at the bucket start.
                    consider(b.saturating_mul(span));
                    break;
                }
            }
        }
        if let Some(&target) = self.overflow.keys().next() {
            let top = self.sizes.len() - 1;
            let (size, span) = (self.sizes[top], self.spans[top]);
            // The first top-level bucket start from which `target` is within the horizon.
            let bucket = (target / span).saturating_sub(size - 1).max(c / span + 1);
            consider(bucket.saturating_mul(span));
        }
        best
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Steps tick by tick and records the tick each item came out at.
    fn fire_ticks(w: &mut Wheel<u64>, until: u64) -> Vec<(u64, u64)> {
        let mut fired = Vec::new();
        let mut out = Vec::new();
        while w.current() < until {
            let next = w.current() + 1;
            w.advance(next, &mut out);
            fired.extend(out.drain(..).map(|id| (id, next)));
        }
        fired
    }

    #[test]
    fn inside_the_first_wheel_fires_on_its_tick() {
        let mut w = Wheel::new(&[10, 6]);
        for t in [1, 5, 9] {
            w.insert(t, t).unwrap();
        }
        assert_eq!(fire_ticks(&mut w, 20), vec![(1, 1), (5, 5), (9, 9)]);
    }

    #[test]
    fn the_current_tick_is_refused_and_the_next_is_accepted() {
        let mut w = Wheel::new(&[10]);
        let mut out = Vec::new();
        w.advance(4, &mut out);
        assert_eq!(w.insert(4, 0), Err(0));
        assert_eq!(w.insert(3, 0), Err(0));
        // Re-arm from inside tick 4's work into the next tick.
        w.insert(5, 5).unwrap();
        assert_eq!(fire_ticks(&mut w, 6), vec![(5, 5)]);
    }

    #[test]
    fn aimrt_b1_carry_case_is_not_early() {
        // Wheel [10, 6], at tick 5, target 22: AimRT fires at 12.
        let mut w = Wheel::new(&[10, 6]);
        let mut out = Vec::new();
        w.advance(5, &mut out);
        w.insert(22, 22).unwrap();
        assert_eq!(fire_ticks(&mut w, 40), vec![(22, 22)]);
    }

    #[test]
    fn across_levels_and_beyond_all_wheels() {
        let mut w = Wheel::new(&[10, 6]);
        let mut out = Vec::new();
        w.advance(7, &mut out);
        let targets = [8, 17, 18, 60, 61, 66, 67, 100, 359, 360, 361, 1000, 5003];
        for t in targets {
            w.insert(t, t).unwrap();
        }
        let fired = fire_ticks(&mut w, 6000);
        assert_eq!(fired, targets.iter().map(|&t| (t, t)).collect::<Vec<_>>());
        assert_eq!(w.len(), 0);
    }

    #[test]
    fn jumps_fire_everything_due_in_order() {
        let mut w = Wheel::new(&[4, 3, 2]);
        for t in [50, 3, 30, 7, 200] {
            w.insert(t, t).unwrap();
        }
        let mut out = Vec::new();
        w.advance(31, &mut out);
        assert_eq!(out, vec![3, 7, 30]);
        out.clear();
        w.advance(10_000, &mut out);
        assert_eq!(out, vec![50, 200]);
    }

    #[test]
    fn next_event_is_never_after_the_next_fire() {
        let mut w = Wheel::new(&[8, 4]);
        assert_eq!(w.next_event(), None);
        w.insert(100, 100).unwrap();
        let mut out = Vec::new();
        let mut wakes = 0;
        while out.is_empty() {
            let e = w.next_event().unwrap();
            assert!(e <= 100 && e > w.current());
            w.advance(e, &mut out);
            wakes += 1;
        }
        assert_eq!((out, w.current()), (vec![100], 100));
        // An idle driver wakes a handful of times, not 100.
        assert!(wakes < 10, "{wakes}");
    }

    /// Random schedules checked against the definition: an item comes out in the
    /// `advance` call that first reaches its tick.
    #[test]
    fn random_schedules_match_the_definition() {
        let mut seed = 0x2545_f491_4f6c_dd1du64;
        let mut rand = move |n: u64| {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            seed % n
        };
        for round in 0..300 {
            let levels = 1 + rand(3) as usize;
            let sizes: Vec<u64> = (0..levels).map(|_| 1 + rand(7)).collect();
            let mut w = Wheel::new(&sizes);
            let mut expected = std::collections::HashMap::new();
            let mut out = Vec::new();
            let mut id = 0u64;
            for _ in 0..200 {
                for _ in 0..rand(4) {
                    let target = w.current() + 1 + rand(500);
                    w.insert(target, id).unwrap();
                    expected.insert(id, target);
                    id += 1;
                }
                let before = w.current();
                let to = before + rand(40);
                w.advance(to, &mut out);
                for fired in out.drain(..) {
                    let t = expected.remove(&fired).expect("fired once");
                    assert!(
                        t > before && t <= to,
                        "round {round} sizes {sizes:?}: item for tick {t} fired in ({before}, {to}]"
                    );
                }
            }
            for (id, t) in &expected {
                assert!(*t > w.current(), "item {id} for tick {t} was lost");
            }
            assert_eq!(w.len(), expected.len());
        }
    }
}
