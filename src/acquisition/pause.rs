//! Pausing a job: a client's `pause` takes effect at the next step boundary (the stage idle
//! where the last frame was taken, nothing half recorded); a controller's feed hold pauses
//! the job mid-move (with `[daemon] on_feed_hold = "pause"`). `resume` lets the engine go
//! on with the next frame of the plan, so no frame is lost or repeated.
//!
//! The engine owns the transitions into `Paused` (only it knows where a boundary is); a
//! client only requests a pause and releases it. Events go to a listener the daemon sets,
//! called on the engine's thread: a `paused` event may come before the `step` events of
//! frames still on their way to the disk.

use crate::acquisition::outcome::StopCause;
use serde::{Deserialize, Serialize};
use std::sync::Mutex;
use std::time::Duration;

/// What the engine does when the controller reports a feed hold mid-move.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum HoldPolicy {
    /// Pause the job; `resume` resumes the controller and re-issues the move.
    #[default]
    Pause,
    /// Fail the job at once, naming where the stage held.
    Fail,
}

/// Why a job is paused.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "cause", rename_all = "snake_case")]
pub enum PauseCause {
    /// A client asked (`pause`): taken at a step boundary.
    Client,
    /// The controller holds (feed hold or safety door) during the move to `target_um`.
    FeedHold { device: String, target_um: f64 },
}

/// A pause or resume, as the engine reports it.
#[derive(Debug, Clone, PartialEq)]
pub enum PauseEvent {
    Paused {
        /// The index of the next frame to take (the frames before it are taken).
        next_index: u32,
        /// Where the stage was when the job paused, when known.
        at_um: Option<f64>,
        cause: PauseCause,
    },
    Resumed {
        next_index: u32,
    },
}

impl PauseEvent {
    /// The reason clients read.
    pub fn reason(&self) -> String {
        match self {
            PauseEvent::Paused { cause, at_um, .. } => match cause {
                PauseCause::Client => "paused by a client".to_string(),
                PauseCause::FeedHold { device, target_um } => format!(
                    "{device}: feed hold at {} during the move to {target_um} µm (the controller \
                     holds: feed hold or safety door); resume to go on",
                    at_um.map_or("an unknown position".into(), |u| format!("{u:.1} µm"))
                ),
            },
            PauseEvent::Resumed { .. } => "resumed".to_string(),
        }
    }
}

/// Where a pause stands.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum PauseState {
    #[default]
    Running,
    /// Asked for; the engine takes it at the next boundary.
    Requested,
    Paused,
}

pub type Listener = Box<dyn Fn(&PauseEvent) + Send + Sync>;

/// A job's pause switch, shared by the clients (request, release) and the engine.
#[derive(Default)]
pub struct Pause {
    state: Mutex<PauseState>,
    /// Where the stage was left by the pause (what `position` reports during it).
    at: Mutex<Option<f64>>,
    listener: Mutex<Option<Listener>>,
}

impl std::fmt::Debug for Pause {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Pause")
            .field("state", &self.state())
            .finish_non_exhaustive()
    }
}

/// How often a paused engine looks for a resume or a stop.
const POLL: Duration = Duration::from_millis(5);

impl Pause {
    pub fn state(&self) -> PauseState {
        *self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn set(&self, s: PauseState) -> PauseState {
        std::mem::replace(
            &mut *self.state.lock().unwrap_or_else(|e| e.into_inner()),
            s,
        )
    }

    /// Where the paused job left its stage.
    pub fn at_um(&self) -> Option<f64> {
        *self.at.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Who hears of pauses and resumes (the daemon: events, the job table).
    pub fn listen(&self, f: Option<Listener>) {
        *self.listener.lock().unwrap_or_else(|e| e.into_inner()) = f;
    }

    /// A client's pause: returns the state after it (`Requested` or, already, `Paused`).
    pub fn request(&self) -> PauseState {
        let mut s = self.state.lock().unwrap_or_else(|e| e.into_inner());
        if *s == PauseState::Running {
            *s = PauseState::Requested;
        }
        *s
    }

    /// A client's resume: a paused job goes on, a pause not yet taken is withdrawn. Returns
    /// the state it was in (`Running`: nothing to resume).
    pub fn release(&self) -> PauseState {
        let mut s = self.state.lock().unwrap_or_else(|e| e.into_inner());
        let was = *s;
        if was != PauseState::Running {
            *s = PauseState::Running;
        }
        was
    }

    /// The engine at a boundary: whether a requested pause starts now.
    pub fn take_request(&self) -> bool {
        let mut s = self.state.lock().unwrap_or_else(|e| e.into_inner());
        let take = *s == PauseState::Requested;
        if take {
            *s = PauseState::Paused;
        }
        take
    }

    /// The engine pauses (at a boundary, or on a hold) and waits for a resume or a stop:
    /// `Err` names the stop.
    pub fn hold_until_resumed(
        &self,
        event: PauseEvent,
        stop: impl Fn() -> Option<StopCause>,
    ) -> Result<(), StopCause> {
        self.hold_until_resumed_with(event, stop, || {})
    }

    /// [`Pause::hold_until_resumed`], calling `meanwhile` at every poll while paused (the
    /// engine serves the live view's frames there).
    pub fn hold_until_resumed_with(
        &self,
        event: PauseEvent,
        stop: impl Fn() -> Option<StopCause>,
        mut meanwhile: impl FnMut(),
    ) -> Result<(), StopCause> {
        let next_index = match &event {
            PauseEvent::Paused {
                next_index,
                at_um,
                cause,
            } => {
                *self.at.lock().unwrap_or_else(|e| e.into_inner()) = *at_um;
                // A boundary pause was taken by `take_request`; a hold pauses here.
                if matches!(cause, PauseCause::FeedHold { .. }) {
                    self.set(PauseState::Paused);
                }
                *next_index
            }
            PauseEvent::Resumed { next_index } => *next_index,
        };
        tracing::info!(next_index, reason = %event.reason(), "job paused");
        self.notify(&event);
        loop {
            if let Some(cause) = stop() {
                return Err(cause);
            }
            if self.state() == PauseState::Running {
                break;
            }
            meanwhile();
            std::thread::sleep(POLL);
        }
        *self.at.lock().unwrap_or_else(|e| e.into_inner()) = None;
        tracing::info!(next_index, "job resumed");
        self.notify(&PauseEvent::Resumed { next_index });
        Ok(())
    }

    fn notify(&self, event: &PauseEvent) {
        if let Some(f) = self
            .listener
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .as_ref()
        {
            f(event);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_request_is_taken_once_and_a_release_withdraws_it() {
        let p = Pause::default();
        assert!(!p.take_request());
        assert_eq!(p.request(), PauseState::Requested);
        assert_eq!(p.release(), PauseState::Requested);
        assert!(!p.take_request(), "withdrawn before the boundary");
        p.request();
        assert!(p.take_request());
        assert_eq!(p.request(), PauseState::Paused);
        assert_eq!(p.release(), PauseState::Paused);
        assert_eq!(p.release(), PauseState::Running);
    }

    #[test]
    fn a_hold_reason_names_the_device_and_both_positions() {
        let e = PauseEvent::Paused {
            next_index: 3,
            at_um: Some(1482.04),
            cause: PauseCause::FeedHold {
                device: "axis".into(),
                target_um: 5000.0,
            },
        };
        assert_eq!(
            e.reason(),
            "axis: feed hold at 1482.0 µm during the move to 5000 µm (the controller holds: \
             feed hold or safety door); resume to go on"
        );
    }
}
