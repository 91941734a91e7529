//! The rig's state as every client sees it (`hello`, `status`): `ready`, `busy` (a job or a
//! rig request is using it) or `fault` (a latched alarm, a lost port: with the device, the
//! reason and the requests that clear it).
//!
//! A fault is set by the worker when the controller itself says so after a job failed on
//! the hardware (its status is `Alarm`, or its port cannot be reached), and cleared only by a
//! rig request (`unlock`, `home`, `reconnect`) that the controller confirms. While in fault,
//! live jobs are refused at submit and jobs queued before it are ended without a session.

use crate::acquisition::StageKind;
use crate::hw::{HwError, MotionState};
use crate::rig::Rig;
use serde::{Deserialize, Serialize};

/// The requests that act on the rig outside a job, run by the worker.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum RigAction {
    /// Clear a latched alarm or error (GRBL `$X`; GCS `ERR?` and servo on).
    Unlock,
    /// The homing cycle (GRBL `$H`; GCS `FRF` or a move to `home_um`).
    Home,
    /// Close and reopen the port, handshake included.
    Reconnect,
    /// Read both stages' positions (`daemon::manual`).
    Position,
    /// A manual move (`daemon::manual`).
    Move,
}

impl RigAction {
    pub fn name(self) -> &'static str {
        match self {
            RigAction::Unlock => "unlock",
            RigAction::Home => "home",
            RigAction::Reconnect => "reconnect",
            RigAction::Position => "position",
            RigAction::Move => "move",
        }
    }
}

/// Why the rig cannot run jobs, and what clears it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct RigFault {
    /// The stage in fault ("axis", "piezo").
    pub device: String,
    /// What the controller said.
    pub reason: String,
    /// The requests that clear it, the first the usual one.
    pub clear_with: Vec<RigAction>,
}

impl RigFault {
    /// The refusal of a job, naming the fault and the request that clears it.
    pub fn refusal(&self) -> String {
        let ways: Vec<String> = self
            .clear_with
            .iter()
            .map(|a| {
                format!(
                    "`{}` (rigctl {} --stage {})",
                    a.name(),
                    a.name(),
                    self.device
                )
            })
            .collect();
        format!(
            "the rig is in fault: {}; clear it with {}",
            self.reason,
            ways.join(" or ")
        )
    }
}

/// The rig state on the wire: `{"state":"ready"}`, `{"state":"busy","job_id":3}`,
/// `{"state":"fault","device":"axis","reason":"…","clear_with":["unlock","home"]}`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default, schemars::JsonSchema)]
#[serde(tag = "state", rename_all = "snake_case")]
pub enum RigState {
    #[default]
    Ready,
    /// A job or a rig request is using the rig (neither: the daemon is asking the
    /// controllers at start).
    Busy {
        /// The running job, if a job is what keeps it busy.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        job_id: Option<u64>,
        /// The rig request running, if that is.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        request: Option<RigAction>,
        /// Rig requests waiting behind it, in order (absent: none).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        waiting: Option<usize>,
    },
    Fault(RigFault),
}

/// What the daemon keeps about the rig besides the job table.
#[derive(Debug, Default)]
pub struct RigCondition {
    pub fault: Option<RigFault>,
    /// A rig request the worker is running.
    pub request: Option<RigAction>,
    /// Live jobs the worker has started (a rig request sent before a job started is
    /// refused when it arrives after).
    pub jobs_started: u64,
    /// The worker has not yet asked the controllers (the daemon just started).
    pub starting: bool,
}

impl RigCondition {
    /// The state, given the running job.
    pub fn state(&self, running_job: Option<u64>) -> RigState {
        if let Some(f) = &self.fault {
            return RigState::Fault(f.clone());
        }
        match (running_job, self.request) {
            (None, None) if !self.starting => RigState::Ready,
            (job_id, request) => RigState::Busy {
                job_id,
                request,
                waiting: None,
            },
        }
    }
}

/// What the controller of `kind` says now: a fault if it is in alarm or cannot be reached.
pub fn probe(rig: &mut Rig, kind: StageKind) -> Option<RigFault> {
    let stage = rig.stage(kind).ok()?;
    match stage.status() {
        Ok(st) if st.state == MotionState::Alarm => Some(RigFault {
            device: stage.name().to_string(),
            reason: format!("{}: in alarm at {:.1} µm", stage.name(), st.position_um),
            clear_with: vec![RigAction::Unlock, RigAction::Home],
        }),
        Ok(_) => None,
        Err(e) => Some(fault_of(&e)),
    }
}

/// A fault from the error the controller gave.
pub fn fault_of(e: &HwError) -> RigFault {
    let device = crate::acquisition::outcome::device_of(e).to_string();
    let clear_with = match e {
        HwError::Alarm { .. } => vec![RigAction::Unlock, RigAction::Home],
        HwError::Controller { .. } => vec![RigAction::Unlock, RigAction::Reconnect],
        _ => vec![RigAction::Reconnect],
    };
    RigFault {
        device,
        reason: e.to_string(),
        clear_with,
    }
}

/// The first fault among the rig's stages (the axis first).
pub fn probe_all(rig: &mut Rig) -> Option<RigFault> {
    let has_piezo = rig.piezo.is_some();
    probe(rig, StageKind::Axis)
        .or_else(|| has_piezo.then(|| probe(rig, StageKind::Piezo)).flatten())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_state_reads_as_documented() {
        let mut c = RigCondition::default();
        assert_eq!(
            serde_json::to_value(c.state(None)).unwrap()["state"],
            "ready"
        );
        let busy = serde_json::to_value(c.state(Some(3))).unwrap();
        assert_eq!(busy, serde_json::json!({"state": "busy", "job_id": 3}));
        c.fault = Some(fault_of(&HwError::PortGone {
            device: "axis".into(),
            message: "cannot open /dev/ttyUSB0".into(),
        }));
        let f = serde_json::to_value(c.state(None)).unwrap();
        assert_eq!(f["state"], "fault");
        assert_eq!(f["device"], "axis");
        assert_eq!(f["clear_with"], serde_json::json!(["reconnect"]));
        let refusal = c.fault.as_ref().unwrap().refusal();
        assert_eq!(
            refusal,
            "the rig is in fault: axis: port gone: cannot open /dev/ttyUSB0; clear it with \
             `reconnect` (rigctl reconnect --stage axis)"
        );
        let back: RigState = serde_json::from_value(f).unwrap();
        assert!(matches!(back, RigState::Fault(_)));
    }
}
