//! When long work stops early: a [`Stop`] is read by the work (lamp walks check it every
//! few dozen walks), [`StopFlag`]s are set by whoever runs it — a server when the client
//! went away or it shuts down — and a time limit stops it by itself.
//!
//! In: flags and an optional instant. Out: [`Stop::is_set`] and why ([`Stop::reason`]).

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

/// A flag one party sets and any number of [`Stop`]s read.
#[derive(Debug, Clone, Default)]
pub struct StopFlag(Arc<AtomicBool>);

impl StopFlag {
    pub fn new() -> StopFlag {
        StopFlag::default()
    }

    /// Asks every work that reads this flag to stop.
    pub fn set(&self) {
        self.0.store(true, Ordering::Relaxed);
    }

    pub fn is_set(&self) -> bool {
        self.0.load(Ordering::Relaxed)
    }
}

/// Why a [`Stop`] fired.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Reason {
    /// One of its flags was set.
    Flag,
    /// Its time ran out.
    Time,
}

/// What long work reads to know whether to stop: any of its flags set, or its instant
/// passed. The default never stops.
#[derive(Debug, Clone, Default)]
pub struct Stop {
    flags: Vec<StopFlag>,
    until: Option<Instant>,
}

impl Stop {
    /// A stop that never fires.
    pub fn never() -> Stop {
        Stop::default()
    }

    /// This stop, also fired by `flag`.
    pub fn with(mut self, flag: &StopFlag) -> Stop {
        self.flags.push(flag.clone());
        self
    }

    /// This stop, also fired at `at` (the earlier instant wins).
    pub fn until(mut self, at: Instant) -> Stop {
        self.until = Some(self.until.map_or(at, |u| u.min(at)));
        self
    }

    /// Whether the work should stop now, and why.
    pub fn reason(&self) -> Option<Reason> {
        if self.flags.iter().any(StopFlag::is_set) {
            Some(Reason::Flag)
        } else if self.until.is_some_and(|u| Instant::now() >= u) {
            Some(Reason::Time)
        } else {
            None
        }
    }

    pub fn is_set(&self) -> bool {
        self.reason().is_some()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn a_stop_fires_on_any_of_its_flags_or_its_time() {
        assert!(!Stop::never().is_set());
        let (a, b) = (StopFlag::new(), StopFlag::new());
        let s = Stop::never().with(&a).with(&b);
        assert!(!s.is_set());
        b.set();
        assert_eq!(s.reason(), Some(Reason::Flag));
        assert!(!Stop::never().with(&a).is_set());
        let late = Instant::now() + Duration::from_secs(3600);
        let s = Stop::never().until(late).until(Instant::now());
        assert_eq!(s.reason(), Some(Reason::Time));
        assert!(!Stop::never().until(late).is_set());
    }
}
