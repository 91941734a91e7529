//! The wire protocol: versioned JSON lines over the Unix socket (docs/protocol.md).
//!
//! A client writes one request object per line; the server answers each with one reply
//! line carrying the request's `id`, and after `subscribe` it also writes event lines.
//! Decoding is strict (unknown fields and kinds are errors) and never panics: every bad line
//! gets an error reply naming what was wrong.

use crate::pipeline::{Combine, Estimator, ProcessOptions, Registration};
use serde::{Deserialize, Serialize};

/// Version of this protocol; requests may carry `"v"` and must match it.
pub const PROTOCOL_VERSION: u32 = 1;
/// Longest request line the server reads; longer lines get a `line_too_long` error.
pub const MAX_LINE_BYTES: usize = 64 * 1024;

/// Which stage a job steps.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum StageKind {
    /// The numerically controlled axis (GRBL).
    #[default]
    Axis,
    /// The piezo flexure (PI GCS).
    Piezo,
}

/// The paper's three cases (Alzarok et al., section 4).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PaperCase {
    /// One raw frame.
    Case1,
    /// Ten frames 100 µm apart, reconstructed at k = 5.
    Case2,
    /// Twenty frames 50 µm apart, reconstructed at k = 10.
    Case3,
}

impl PaperCase {
    pub const ALL: [PaperCase; 3] = [PaperCase::Case1, PaperCase::Case2, PaperCase::Case3];

    pub fn scan(self) -> CaseScan {
        let (name, frames, step_um, k) = match self {
            PaperCase::Case1 => ("case1", 1, 0.0, 1),
            PaperCase::Case2 => ("case2", 10, 100.0, 5),
            PaperCase::Case3 => ("case3", 20, 50.0, 10),
        };
        CaseScan {
            name: name.to_string(),
            frames,
            step_um,
            k,
        }
    }
}

/// Where a job's per-frame displacements come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum JobRegistration {
    /// Measured in the image (the paper's).
    #[default]
    Image,
    /// From the commanded positions (the config's and `rigctl process`'s "positions").
    #[serde(alias = "positions")]
    Commanded,
    /// From the interferometer's reading at each frame (the job fails at a frame without one).
    Interferometer,
}

impl From<Registration> for JobRegistration {
    fn from(r: Registration) -> JobRegistration {
        match r {
            Registration::Image => JobRegistration::Image,
            Registration::Positions => JobRegistration::Commanded,
        }
    }
}

/// One scan of a job: `frames` frames `step_um` apart, reconstructed at `k`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CaseScan {
    pub name: String,
    pub frames: u32,
    pub step_um: f64,
    pub k: u32,
}

fn default_settle_ms() -> u64 {
    20
}
fn default_one() -> u32 {
    1
}
fn default_true() -> bool {
    true
}

/// A capture job as a client submits it. Either a single scan (`step_um`, `steps`, `k`) or a
/// study of the paper's cases (`study`), repeated `repeats` times.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JobSpec {
    #[serde(default)]
    pub stage: StageKind,
    /// Distance between frames of a scan.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub step_um: Option<f64>,
    /// Number of frames of a scan.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub steps: Option<u32>,
    /// Upsampling factor of a scan's reconstruction.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub k: Option<u32>,
    /// Run these of the paper's cases instead of a single scan.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub study: Option<Vec<PaperCase>>,
    /// Wait after each move before grabbing.
    #[serde(default = "default_settle_ms")]
    pub settle_ms: u64,
    /// Processing left out (None) takes the rig's `[pipeline]` default, else the protocol's;
    /// the daemon records the values it resolved (docs/protocol.md).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub estimator: Option<Estimator>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub combine: Option<Combine>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub registration: Option<JobRegistration>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub whole_frame: Option<bool>,
    #[serde(default = "default_one")]
    pub repeats: u32,
    /// Absolute start of the first scan; default: where the stage is.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub start_um: Option<f64>,
    /// Each repeat starts this much further than the previous one (sub-pixel start phases).
    #[serde(default)]
    pub repeat_shift_um: f64,
    /// Process the frames while capturing (false: capture and record only).
    #[serde(default = "default_true")]
    pub process: bool,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub label: Option<String>,
}

impl Default for JobSpec {
    fn default() -> Self {
        JobSpec {
            stage: StageKind::Axis,
            step_um: None,
            steps: None,
            k: None,
            study: None,
            settle_ms: default_settle_ms(),
            estimator: None,
            combine: None,
            registration: None,
            whole_frame: None,
            repeats: 1,
            start_um: None,
            repeat_shift_um: 0.0,
            process: true,
            label: None,
        }
    }
}

/// Processing settings, each optional: a replay's overrides of the recorded ones, and a
/// rig's `[pipeline]` defaults for what a job leaves out.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct Processing {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub k: Option<u32>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub estimator: Option<Estimator>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub combine: Option<Combine>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub registration: Option<JobRegistration>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub whole_frame: Option<bool>,
}

/// What a client asks. Tagged by `kind`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum Request {
    /// Protocol and daemon versions, rig description.
    Hello,
    Submit {
        job: JobSpec,
    },
    /// One job's state, or the daemon's (running job, queue) without `job_id`.
    Status {
        #[serde(default, skip_serializing_if = "Option::is_none")]
        job_id: Option<u64>,
    },
    /// Jobs known to this daemon run and the sessions on disk.
    List,
    Cancel {
        job_id: u64,
    },
    /// A finished job's result (per-run measurements and the study summary).
    Result {
        job_id: u64,
    },
    /// Follow events: of one job, or of every job without `job_id`.
    Subscribe {
        #[serde(default, skip_serializing_if = "Option::is_none")]
        job_id: Option<u64>,
    },
    /// Run a recorded session again through the job path in simulation.
    Replay {
        session: String,
        #[serde(default)]
        processing: Processing,
    },
}

/// Error codes of error replies.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ErrorCode {
    /// Not JSON, or not an object.
    Malformed,
    /// JSON of the wrong shape: unknown kind or field, wrong type, missing field.
    BadRequest,
    /// Protocol version mismatch.
    Version,
    LineTooLong,
    /// A well-formed job the rig cannot run (limits, zero step, disk space).
    Rejected,
    NotFound,
    /// The daemon is shutting down.
    Unavailable,
    Internal,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, thiserror::Error)]
#[error("{code:?}: {message}")]
pub struct ProtoError {
    pub code: ErrorCode,
    pub message: String,
}

impl ProtoError {
    pub fn new(code: ErrorCode, message: impl Into<String>) -> ProtoError {
        ProtoError {
            code,
            message: message.into(),
        }
    }
}

/// A decoded request line: its `id` (echoed in the reply) and the request.
#[derive(Debug, Clone, PartialEq)]
pub struct Envelope {
    pub id: Option<serde_json::Value>,
    pub request: Request,
}

/// Decode one request line (without its newline). On error, also returns the `id` when the
/// line was an object that had one, so the error reply can carry it.
pub fn decode_request(line: &[u8]) -> Result<Envelope, (Option<serde_json::Value>, ProtoError)> {
    if line.len() > MAX_LINE_BYTES {
        return Err((
            None,
            ProtoError::new(
                ErrorCode::LineTooLong,
                format!(
                    "line of {} bytes is over the {MAX_LINE_BYTES}-byte limit",
                    line.len()
                ),
            ),
        ));
    }
    let value: serde_json::Value = serde_json::from_slice(line).map_err(|e| {
        (
            None,
            ProtoError::new(ErrorCode::Malformed, format!("not JSON: {e}")),
        )
    })?;
    let serde_json::Value::Object(mut map) = value else {
        return Err((
            None,
            ProtoError::new(ErrorCode::Malformed, "a request must be a JSON object"),
        ));
    };
    let id = map.remove("id");
    if let Some(id) = &id {
        if !(id.is_number() || id.is_string()) {
            return Err((
                None,
                ProtoError::new(ErrorCode::BadRequest, "`id` must be a number or a string"),
            ));
        }
    }
    if let Some(v) = map.remove("v") {
        if v.as_u64() != Some(PROTOCOL_VERSION as u64) {
            return Err((
                id,
                ProtoError::new(
                    ErrorCode::Version,
                    format!("protocol version {v} is not supported (this daemon speaks {PROTOCOL_VERSION})"),
                ),
            ));
        }
    }
    match serde_json::from_value::<Request>(serde_json::Value::Object(map)) {
        Ok(request) => Ok(Envelope { id, request }),
        Err(e) => Err((
            id,
            ProtoError::new(ErrorCode::BadRequest, format!("bad request: {e}")),
        )),
    }
}

/// One line the server writes: a reply or an event.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum ServerLine {
    Reply(Reply),
    Event(Event),
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Reply {
    pub v: u32,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub id: Option<serde_json::Value>,
    pub ok: bool,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub result: Option<serde_json::Value>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<ProtoError>,
}

impl Reply {
    pub fn ok(id: Option<serde_json::Value>, result: serde_json::Value) -> Reply {
        Reply {
            v: PROTOCOL_VERSION,
            id,
            ok: true,
            result: Some(result),
            error: None,
        }
    }
    pub fn err(id: Option<serde_json::Value>, error: ProtoError) -> Reply {
        Reply {
            v: PROTOCOL_VERSION,
            id,
            ok: false,
            result: None,
            error: Some(error),
        }
    }
}

/// Time spent in each phase of one step, milliseconds.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, Default)]
pub struct StepTimings {
    pub move_ms: f64,
    pub settle_ms: f64,
    pub grab_ms: f64,
    /// Processing of this frame (runs while the axis moves to the next step); `None` when
    /// the job does not process.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub process_ms: Option<f64>,
}

/// Something that happened to a job. Every event carries the job id.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Event {
    pub v: u32,
    pub job_id: u64,
    #[serde(flatten)]
    pub body: EventBody,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "event", rename_all = "snake_case")]
pub enum EventBody {
    Accepted {
        queue_position: usize,
        total_frames: u32,
        /// The job as it will run: every processing default resolved.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        job: Option<Box<JobSpec>>,
    },
    Started {
        session: String,
        total_frames: u32,
    },
    /// A frame was captured and is on disk.
    Step {
        /// Index over the whole job (the session's `steps.csv` index).
        index: u32,
        run: u32,
        case: String,
        repeat: u32,
        commanded_um: f64,
        axis_um: f64,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        interferometer_um: Option<f64>,
        timings: StepTimings,
        total_frames: u32,
    },
    /// A frame was processed (runs behind the capture).
    Processed {
        index: u32,
        process_ms: f64,
        targets_found: usize,
    },
    /// One run (one case, one repeat) has its measurement.
    Result {
        run: u32,
        case: String,
        repeat: u32,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        objects: Option<usize>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        error: Option<String>,
    },
    Finished {
        session: String,
    },
    Failed {
        reason: String,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        session: Option<String>,
    },
    Cancelled {
        #[serde(default, skip_serializing_if = "Option::is_none")]
        session: Option<String>,
    },
}

impl EventBody {
    /// Whether this event ends the job.
    pub fn is_terminal(&self) -> bool {
        matches!(
            self,
            EventBody::Finished { .. } | EventBody::Failed { .. } | EventBody::Cancelled { .. }
        )
    }
}

/// Encode a server line as JSON + newline.
pub fn encode(line: &ServerLine) -> Vec<u8> {
    let mut v = serde_json::to_vec(line).expect("server lines are plain data");
    v.push(b'\n');
    v
}

/// Processing options for one scan of a job.
pub fn process_options(
    spec: &JobSpec,
    k: u32,
    scale_um_per_px: f64,
    axis_dir: [f64; 2],
) -> ProcessOptions {
    let mut o = ProcessOptions {
        scale_um_per_px,
        k,
        estimator: spec.estimator.unwrap_or_default(),
        whole_frame: spec.whole_frame.unwrap_or(false),
        axis_dir,
        registration: match spec.registration.unwrap_or_default() {
            JobRegistration::Image => Registration::Image,
            JobRegistration::Commanded | JobRegistration::Interferometer => Registration::Positions,
        },
        ..ProcessOptions::default()
    };
    if let Some(c) = spec.combine {
        o.combine = c;
    } else if k > 1 {
        o.combine = Combine::Interp;
    }
    o
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_submit_line_decodes_with_defaults() {
        let e = decode_request(
            br#"{"v":1,"id":7,"kind":"submit","job":{"step_um":50,"steps":20,"k":10}}"#,
        )
        .unwrap();
        assert_eq!(e.id, Some(serde_json::json!(7)));
        let Request::Submit { job } = e.request else {
            panic!("not a submit")
        };
        assert_eq!(job.steps, Some(20));
        assert_eq!(job.settle_ms, 20);
        assert!(job.process);
    }

    #[test]
    fn unknown_fields_kinds_and_versions_are_named() {
        let (_, e) = decode_request(br#"{"kind":"status","jobid":3}"#).unwrap_err();
        assert_eq!(e.code, ErrorCode::BadRequest);
        assert!(e.message.contains("jobid"), "{}", e.message);
        let (_, e) = decode_request(br#"{"kind":"launch"}"#).unwrap_err();
        assert!(e.message.contains("launch"), "{}", e.message);
        let (id, e) = decode_request(br#"{"v":2,"id":"a","kind":"list"}"#).unwrap_err();
        assert_eq!((e.code, id), (ErrorCode::Version, Some("a".into())));
        let (_, e) = decode_request(br#"{"kind":"submit","job":{"step_um":"fifty"}}"#).unwrap_err();
        assert!(
            e.message.contains("step_um") || e.message.contains("fifty"),
            "{}",
            e.message
        );
        let (_, e) = decode_request(b"[1,2]").unwrap_err();
        assert_eq!(e.code, ErrorCode::Malformed);
    }

    #[test]
    fn events_round_trip_with_the_job_id() {
        let ev = ServerLine::Event(Event {
            v: 1,
            job_id: 4,
            body: EventBody::Cancelled { session: None },
        });
        let bytes = encode(&ev);
        let text = std::str::from_utf8(&bytes).unwrap();
        assert!(text.contains(r#""job_id":4"#) && text.contains(r#""event":"cancelled""#));
        let back: ServerLine = serde_json::from_slice(&bytes).unwrap();
        assert_eq!(back, ev);
    }

    #[test]
    fn processing_names_the_commanded_positions_either_way() {
        // "positions" is what the config and `rigctl process` call them (and what manifests
        // recorded a config rig's default as); the protocol's name is "commanded".
        for name in ["commanded", "positions"] {
            let p: Processing = serde_json::from_str(&format!(
                r#"{{"registration":"{name}","whole_frame":true}}"#
            ))
            .unwrap();
            assert_eq!(p.registration, Some(JobRegistration::Commanded));
            assert_eq!(p.whole_frame, Some(true));
        }
        assert_eq!(
            JobRegistration::from(Registration::Positions),
            JobRegistration::Commanded
        );
    }

    #[test]
    fn positions_come_back_bit_for_bit() {
        // A reading the default float parser returns one ulp off (serde_json without
        // `float_roundtrip`): a client must see the very position the daemon recorded.
        let um = 1698.0848575209213_f64;
        let ev = ServerLine::Event(Event {
            v: 1,
            job_id: 1,
            body: EventBody::Step {
                index: 0,
                run: 0,
                case: "scan".into(),
                repeat: 0,
                commanded_um: um,
                axis_um: um,
                interferometer_um: Some(um),
                timings: StepTimings {
                    move_ms: 0.1,
                    settle_ms: 0.2,
                    grab_ms: 0.3,
                    process_ms: None,
                },
                total_frames: 1,
            },
        });
        let back: ServerLine = serde_json::from_slice(&encode(&ev)).unwrap();
        let ServerLine::Event(Event {
            body: EventBody::Step { axis_um, .. },
            ..
        }) = back
        else {
            panic!("not a step event: {back:?}")
        };
        assert_eq!(axis_um.to_bits(), um.to_bits());
    }
}
