//! How often a controller may be asked for a status report: a token bucket.
//!
//! GRBL's interface document asks for `?` at 5 Hz at most ("10 Hz may be possible"): every
//! report costs the firmware's main loop, which also feeds the stepper. A bucket keeps the
//! average rate at `rate_hz` over any stretch of time, and lets two reports come close
//! together when they are needed at once (the report that confirms a move's end, right
//! after one that followed the move).

use std::time::{Duration, Instant};

/// Reports that may be asked for back to back before the average rate applies.
const BURST: f64 = 2.0;

/// A rate budget for status polls.
#[derive(Debug, Clone)]
pub struct PollBudget {
    rate_hz: f64,
    tokens: f64,
    at: Instant,
}

impl PollBudget {
    /// A full budget at `rate_hz` (finite and positive: checked by the driver's options).
    pub fn new(rate_hz: f64, now: Instant) -> PollBudget {
        PollBudget {
            rate_hz,
            tokens: BURST,
            at: now,
        }
    }

    fn refill(&mut self, now: Instant) {
        let dt = now.saturating_duration_since(self.at).as_secs_f64();
        self.tokens = (self.tokens + dt * self.rate_hz).min(BURST);
        self.at = now.max(self.at);
    }

    /// How long from `now` until a poll fits the budget.
    pub fn wait(&mut self, now: Instant) -> Duration {
        self.refill(now);
        if self.tokens >= 1.0 {
            Duration::ZERO
        } else {
            Duration::from_secs_f64((1.0 - self.tokens) / self.rate_hz)
        }
    }

    /// Count a poll sent at `now`. A poll outside the budget (a stop that must see the
    /// axis brake) empties it rather than going into debt.
    pub fn spend(&mut self, now: Instant) {
        self.refill(now);
        self.tokens = (self.tokens - 1.0).max(0.0);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Polls sent as soon as the budget allows, over `secs`: how many.
    fn polls_in(rate_hz: f64, secs: f64) -> u32 {
        let t0 = Instant::now();
        let mut b = PollBudget::new(rate_hz, t0);
        let mut now = t0;
        let mut n = 0;
        loop {
            now += b.wait(now);
            if now.duration_since(t0).as_secs_f64() > secs {
                return n;
            }
            b.spend(now);
            n += 1;
        }
    }

    #[test]
    fn the_average_rate_holds_over_any_stretch_after_a_burst_of_two() {
        // 2 at once, then one every 200 ms: 2 + 5 × 10 s.
        assert_eq!(polls_in(5.0, 10.0), 52);
        assert_eq!(polls_in(10.0, 1.0), 12);
    }

    #[test]
    fn a_third_poll_at_once_waits_a_fifth_of_a_second() {
        let t0 = Instant::now();
        let mut b = PollBudget::new(5.0, t0);
        b.spend(t0);
        assert_eq!(b.wait(t0), Duration::ZERO);
        b.spend(t0);
        let w = b.wait(t0).as_secs_f64();
        assert!((w - 0.2).abs() < 1e-9, "{w}");
        // Half a period later, half the wait is left.
        let w = b.wait(t0 + Duration::from_millis(100)).as_secs_f64();
        assert!((w - 0.1).abs() < 1e-9, "{w}");
    }

    #[test]
    fn an_unbudgeted_poll_empties_the_bucket_without_debt() {
        let t0 = Instant::now();
        let mut b = PollBudget::new(5.0, t0);
        for _ in 0..10 {
            b.spend(t0);
        }
        let w = b.wait(t0).as_secs_f64();
        assert!((w - 0.2).abs() < 1e-9, "{w}");
    }
}
