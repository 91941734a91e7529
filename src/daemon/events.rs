//! The event bus: every job event goes to every subscriber (each filters by job id).

use crate::daemon::protocol::{Event, EventBody, PROTOCOL_VERSION};
use tokio::sync::broadcast;

/// Events a slow subscriber may fall behind by before it is told it lost some.
const CAPACITY: usize = 4096;

#[derive(Clone)]
pub struct EventBus {
    tx: broadcast::Sender<Event>,
}

impl Default for EventBus {
    fn default() -> Self {
        EventBus {
            tx: broadcast::channel(CAPACITY).0,
        }
    }
}

impl EventBus {
    /// Publish; having no subscriber is normal.
    pub fn emit(&self, job_id: u64, body: EventBody) {
        let _ = self.tx.send(Event {
            v: PROTOCOL_VERSION,
            job_id,
            body,
        });
    }

    pub fn subscribe(&self) -> broadcast::Receiver<Event> {
        self.tx.subscribe()
    }
}
