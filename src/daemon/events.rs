//! The event bus: every job event goes to every subscriber (each filters by job id).
//!
//! An event is encoded once, when it is emitted, and its line is shared by every
//! subscriber's output queue. The channel holds at most [`CAPACITY`] events, and each is
//! dropped once every subscriber has taken it, so what the bus holds is bounded by
//! `CAPACITY` x the longest event line, with or without subscribers.

use crate::daemon::outbox::Line;
use crate::daemon::protocol::{encode, Event, EventBody, ServerLine, PROTOCOL_VERSION};
use tokio::sync::broadcast;

/// Events a subscriber's forwarder may fall behind by before it is told it lost some. The
/// forwarders never wait (a full client queue drops the event), so this only covers a
/// forwarder not yet scheduled.
pub const CAPACITY: usize = 1024;

/// An event as published: its job, whether it ends the job, its encoded line.
#[derive(Clone, Debug)]
pub struct Published {
    pub job_id: u64,
    pub terminal: bool,
    pub line: Line,
}

#[derive(Clone)]
pub struct EventBus {
    tx: broadcast::Sender<Published>,
}

impl Default for EventBus {
    fn default() -> Self {
        EventBus {
            tx: broadcast::channel(CAPACITY).0,
        }
    }
}

impl EventBus {
    /// Publish; having no subscriber is normal (nothing is encoded or kept then).
    pub fn emit(&self, job_id: u64, body: EventBody) {
        if self.tx.receiver_count() == 0 {
            return;
        }
        let terminal = body.is_terminal();
        let line = encode(&ServerLine::Event(Event {
            v: PROTOCOL_VERSION,
            job_id,
            body,
        }));
        let _ = self.tx.send(Published {
            job_id,
            terminal,
            line: line.into(),
        });
    }

    pub fn subscribe(&self) -> broadcast::Receiver<Published> {
        self.tx.subscribe()
    }
}
