//! The wire protocol: versioned JSON lines over the Unix socket (docs/protocol.md).
//!
//! A client writes one request object per line; the server answers each with one reply
//! line carrying the request's `id`, and after `subscribe` it also writes event lines.
//! Decoding is strict (unknown fields and kinds are errors) and never panics: every bad line
//! gets an error reply naming what was wrong.

use crate::acquisition::outcome::EndDetail;
use crate::acquisition::record::{StepRecord, StepTimings};
use crate::acquisition::{JobSpec, Processing, StageKind};
use crate::daemon::live_view::wire::{PreviewReply, PreviewStopReply};
use crate::daemon::strict_json;
use crate::hw::{MotionState, StageMachine};
use crate::rig::RigMode;
use crate::session::SessionState;
use serde::{Deserialize, Serialize};
use std::path::PathBuf;

pub use crate::versions::PROTOCOL_VERSION;
// The replies' types that live beside the code that makes them, named here for clients.
pub use crate::daemon::jobs::JobStatus;
pub use crate::daemon::live_view::wire::{SnapReply, ViewFrame, ViewTarget, MAX_FPS, MIN_FPS};
pub use crate::daemon::manual::{
    LaserReading, MoveReply, PositionReply, PositionSource, StageReading, StopReply,
};
pub use crate::daemon::rig_state::{RigAction, RigState};
pub use crate::daemon::schema::document_text as schema_text;
pub use crate::daemon::timing::EtaBasis;
/// Longest request line the server reads; longer lines get a `line_too_long` error.
pub const MAX_LINE_BYTES: usize = 64 * 1024;
/// Jobs and sessions a `list` page holds when the request gives no `limit`.
pub const LIST_DEFAULT: u32 = 100;
/// Most jobs and sessions a `list` page holds (a larger `limit` is refused).
pub const LIST_MAX: u32 = 1000;
/// Largest integer `id` echoed: 2^53 - 1, the largest every JSON reader (JavaScript's
/// numbers, any double) holds exactly. Larger integers and fractions are refused.
pub const MAX_ID: u64 = (1 << 53) - 1;

/// What a client asks. Tagged by `kind`. (Its schema also has the line's `v` and `id`:
/// `decode_request` takes them off before the request is decoded.)
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
#[schemars(transform = crate::daemon::schema::request_envelope)]
pub enum Request {
    /// Protocol and daemon versions, rig description. (A struct variant, not a unit one: serde
    /// lets unknown fields through on an internally tagged unit variant.)
    Hello {},
    Submit {
        job: JobSpec,
    },
    /// One job's state, or the daemon's (running job, queue) without `job_id`.
    Status {
        #[serde(default, skip_serializing_if = "Option::is_none")]
        job_id: Option<u64>,
    },
    /// Jobs known to this daemon run and the sessions on disk: a page of each, newest first.
    List {
        /// At most this many jobs and this many sessions (100 when left out, at most 1000:
        /// `LIST_DEFAULT`, `LIST_MAX`).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        limit: Option<u32>,
        /// Only those with a job id below this one (the previous page's `next_before`).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        before: Option<u64>,
    },
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
    /// Clear a latched alarm or error on a stage (GRBL `$X`; GCS `ERR?`, servo on).
    /// `stage`: the stage in fault, else the axis.
    Unlock {
        #[serde(default, skip_serializing_if = "Option::is_none")]
        stage: Option<StageKind>,
    },
    /// Run a stage's homing (GRBL `$H`; GCS `FRF` or a move to `home_um`).
    Home {
        #[serde(default, skip_serializing_if = "Option::is_none")]
        stage: Option<StageKind>,
    },
    /// Close and reopen a stage's port, handshake included.
    Reconnect {
        #[serde(default, skip_serializing_if = "Option::is_none")]
        stage: Option<StageKind>,
    },
    /// One fresh frame now, with the stages' positions and the targets found in it
    /// (docs/protocol.md, "Live view").
    Snap {
        /// 0 < scale <= 1 (default 1).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        scale: Option<f64>,
        /// x, y, width, height in frame px (default: the whole frame).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        crop: Option<[u32; 4]>,
    },
    /// Preview events: the latest frame, at most `max_fps` a second (one per connection; a
    /// new one replaces it).
    Preview {
        max_fps: f64,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        scale: Option<f64>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        crop: Option<[u32; 4]>,
    },
    /// End this connection's preview.
    PreviewStop {},
    /// Both stages' positions and motion states as the controllers report them.
    Position {},
    /// Move a stage outside a job: `to_um` (absolute) or `by_um` (relative), one of them;
    /// the soft limits and `max_step_um` apply. Replies when the move ends (or is stopped).
    Move {
        stage: StageKind,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        to_um: Option<f64>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        by_um: Option<f64>,
    },
    /// Stop a manual move under way (a job: `cancel` or `pause` it).
    Stop {},
    /// Pause a running job at its next step boundary.
    Pause {
        job_id: u64,
    },
    /// Let a paused job go on with its next frame.
    Resume {
        job_id: u64,
    },
    /// Queue a new job that takes an interrupted (incomplete, failed or cancelled) session's
    /// plan on from its first missing frame, linked to it (docs/sessions.md, "Resume").
    ResumeSession {
        session: String,
    },
}

/// The request kinds this daemon serves, one per [`Request`] variant (`hello` lists them).
/// A new request adds its kind here: a test (`daemon::schema`) fails while one is missing.
pub const REQUEST_KINDS: &[&str] = &[
    "hello",
    "submit",
    "status",
    "list",
    "cancel",
    "result",
    "subscribe",
    "replay",
    "unlock",
    "home",
    "reconnect",
    "snap",
    "preview",
    "preview_stop",
    "position",
    "move",
    "stop",
    "pause",
    "resume",
    "resume_session",
];

impl Request {
    /// The rig request this is, if it is one (`unlock`, `home`, `reconnect`).
    pub fn rig_action(&self) -> Option<(RigAction, Option<StageKind>)> {
        match *self {
            Request::Unlock { stage } => Some((RigAction::Unlock, stage)),
            Request::Home { stage } => Some((RigAction::Home, stage)),
            Request::Reconnect { stage } => Some((RigAction::Reconnect, stage)),
            _ => None,
        }
    }
}

/// Error codes of error replies.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
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
    /// The rig is running a job or another rig request.
    Busy,
    /// A rig request the controller refused or failed.
    Hardware,
    Internal,
    /// A code this build does not know (a newer daemon's): clients read it, the daemon
    /// never sends it.
    #[serde(other)]
    #[schemars(skip)]
    Other,
}

#[derive(
    Debug, Clone, PartialEq, Serialize, Deserialize, thiserror::Error, schemars::JsonSchema,
)]
#[error("{}: {message}", crate::text::wire_name(code))]
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
    let value = strict_json::parse(line).map_err(|e| {
        let message = match e.is_data() {
            // A duplicate key: well-formed JSON of a shape the protocol refuses.
            true => return (None, ProtoError::new(ErrorCode::BadRequest, e.to_string())),
            false => format!("not JSON: {e}"),
        };
        (None, ProtoError::new(ErrorCode::Malformed, message))
    })?;
    let serde_json::Value::Object(mut map) = value else {
        return Err((
            None,
            ProtoError::new(ErrorCode::Malformed, "a request must be a JSON object"),
        ));
    };
    let id = map.remove("id");
    if let Some(id) = &id {
        check_id(id).map_err(|e| (None, e))?;
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
    if let Err(e) = check_objects(&map) {
        return Err((id, e));
    }
    match serde_json::from_value::<Request>(serde_json::Value::Object(map)) {
        Ok(request) => Ok(Envelope { id, request }),
        Err(e) => Err((
            id,
            ProtoError::new(ErrorCode::BadRequest, format!("bad request: {e}")),
        )),
    }
}

/// An `id` is echoed exactly: a string, or an integer within ±[`MAX_ID`].
fn check_id(id: &serde_json::Value) -> Result<(), ProtoError> {
    let ok = match id {
        serde_json::Value::String(_) => true,
        serde_json::Value::Number(n) => match (n.as_u64(), n.as_i64()) {
            (Some(u), _) => u <= MAX_ID,
            (None, Some(i)) => i.unsigned_abs() <= MAX_ID,
            (None, None) => false,
        },
        _ => false,
    };
    match ok {
        true => Ok(()),
        false => Err(ProtoError::new(
            ErrorCode::BadRequest,
            format!(
                "`id` must be a string or an integer within ±{MAX_ID} (2^53 - 1), got {}",
                short(id)
            ),
        )),
    }
}

/// Fields that hold a document must hold an object: serde would also take a struct as a
/// JSON array of its fields in order (`"job":[...]`), which no client means. (Elsewhere such
/// a field is unknown, and serde names it.)
fn check_objects(map: &serde_json::Map<String, serde_json::Value>) -> Result<(), ProtoError> {
    let field = match map.get("kind").and_then(|k| k.as_str()) {
        Some("submit") => "job",
        Some("replay") => "processing",
        _ => return Ok(()),
    };
    match map.get(field) {
        None | Some(serde_json::Value::Object(_)) => Ok(()),
        Some(other) => Err(ProtoError::new(
            ErrorCode::BadRequest,
            format!("`{field}` must be a JSON object, got {}", kind_of(other)),
        )),
    }
}

fn kind_of(v: &serde_json::Value) -> &'static str {
    match v {
        serde_json::Value::Null => "null",
        serde_json::Value::Bool(_) => "a boolean",
        serde_json::Value::Number(_) => "a number",
        serde_json::Value::String(_) => "a string",
        serde_json::Value::Array(_) => "an array",
        serde_json::Value::Object(_) => "an object",
    }
}

/// A value for a message, cut to 40 characters.
fn short(v: &serde_json::Value) -> String {
    let s = v.to_string();
    match s.char_indices().nth(40) {
        Some((i, _)) => format!("{}...", &s[..i]),
        None => s,
    }
}

/// One line the server writes: a reply or an event.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum ServerLine {
    Reply(Reply),
    Event(Event),
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct Reply {
    #[schemars(schema_with = "crate::daemon::schema::version")]
    pub v: u32,
    /// The request's `id`, echoed (none on a line that answers no request).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(schema_with = "crate::daemon::schema::id")]
    pub id: Option<serde_json::Value>,
    pub ok: bool,
    /// The request's result: one shape per request kind (`ReplyBody`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(with = "ReplyBody")]
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

/// Something that happened to a job. Every event carries the job id.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct Event {
    #[schemars(schema_with = "crate::daemon::schema::version")]
    pub v: u32,
    pub job_id: u64,
    #[serde(flatten)]
    pub body: EventBody,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
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
        /// A plan that moves the piezo besides the axis: its commanded and settled
        /// positions (`commanded_um`/`axis_um` are then the axis's).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        piezo_commanded_um: Option<f64>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        piezo_um: Option<f64>,
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
        /// The reason's fields: kind, device, file, where the stage was left.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        detail: Option<EndDetail>,
    },
    Cancelled {
        #[serde(default, skip_serializing_if = "Option::is_none")]
        session: Option<String>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        reason: Option<String>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        detail: Option<EndDetail>,
    },
    /// A live-view frame, after `preview` (`job_id` 0: no job, the live view grabbed it).
    Preview(Box<ViewFrame>),
    /// The job paused: at a step boundary (a client's `pause`) or mid-move (a feed hold).
    Paused {
        /// The next frame to take; the frames before it are taken.
        next_index: u32,
        /// Where the stage was left, when known.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        at_um: Option<f64>,
        /// `client` or `feed_hold`.
        cause: String,
        reason: String,
    },
    /// The job goes on with frame `next_index`.
    Resumed {
        next_index: u32,
    },
    /// At the start of a job: the calibration it applies (or why none), with its warnings
    /// (stale, another scale, board or frame size).
    Calibration(crate::calibration_note::CalibrationNote),
    /// A calibration job fitted its scan: the record, now the data root's current one.
    Calibrated(Box<crate::calibration_note::Calibrated>),
}

/// The event kinds this daemon sends, one per [`EventBody`] variant (`hello` lists them).
/// A new event adds its kind here: a test (`daemon::schema`) fails while one is missing.
pub const EVENT_KINDS: &[&str] = &[
    "accepted",
    "started",
    "step",
    "processed",
    "result",
    "finished",
    "failed",
    "cancelled",
    "preview",
    "paused",
    "resumed",
    "calibration",
    "calibrated",
];

impl EventBody {
    /// Whether this event ends the job.
    pub fn is_terminal(&self) -> bool {
        matches!(
            self,
            EventBody::Finished { .. } | EventBody::Failed { .. } | EventBody::Cancelled { .. }
        )
    }
}

impl EventBody {
    /// A queued job that ends before it started.
    pub fn cancelled_in_queue(reason: &str) -> EventBody {
        EventBody::Cancelled {
            session: None,
            reason: Some(reason.into()),
            detail: None,
        }
    }

    /// The `step` event of a recorded step.
    pub fn step(rec: &StepRecord) -> EventBody {
        EventBody::Step {
            index: rec.index,
            run: rec.run,
            case: rec.case.clone(),
            repeat: rec.repeat,
            commanded_um: rec.commanded_um,
            axis_um: rec.axis_um,
            interferometer_um: rec.interferometer_um,
            timings: rec.timings,
            total_frames: rec.total_frames,
            piezo_commanded_um: rec.piezo_commanded_um,
            piezo_um: rec.piezo_um,
        }
    }
}

/// The rig as `hello` describes it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct RigSummary {
    pub mode: RigMode,
    pub axis_limits_um: [f64; 2],
    pub piezo_limits_um: Option<[f64; 2]>,
    pub default_start_um: f64,
    pub scale_um_per_px: f64,
    pub frame_size: (u32, u32),
    pub job_defaults: Processing,
    /// The axis controller's own motion settings (GRBL: `$100`, `$110`, `$120`, read at
    /// connect), when it tells them.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub axis_machine: Option<StageMachine>,
    /// The camera: the sim's profile (`sim: webcam`), or the configured driver and device.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub camera: Option<String>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct HelloReply {
    pub protocol: u32,
    pub rigd: String,
    pub rig: RigSummary,
    pub data_root: PathBuf,
    /// `ready`, `busy` or `fault` (with its reason and what clears it).
    #[serde(default)]
    pub rig_state: RigState,
    /// What this daemon serves and sends.
    #[serde(default)]
    pub capabilities: Capabilities,
}

/// `hello`'s list of what this daemon speaks: a client can check for a request before it
/// sends it, and knows which event kinds to expect (it must skip others: docs/protocol.md).
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize, schemars::JsonSchema)]
pub struct Capabilities {
    /// The request kinds it serves.
    pub requests: Vec<String>,
    /// The event kinds it may send.
    pub events: Vec<String>,
}

impl Capabilities {
    /// This build's: [`REQUEST_KINDS`] and [`EVENT_KINDS`].
    pub fn this_daemon() -> Capabilities {
        let owned = |kinds: &[&str]| kinds.iter().map(|k| k.to_string()).collect();
        Capabilities {
            requests: owned(REQUEST_KINDS),
            events: owned(EVENT_KINDS),
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct SubmitReply {
    pub job_id: u64,
    /// Jobs ahead of this one.
    pub queue_position: usize,
    pub total_frames: u32,
    /// The job as it will run: every processing default resolved.
    pub job: JobSpec,
    /// The most memory its processing is estimated to hold, MB: what was checked against
    /// `[daemon] max_job_memory_mb`. It counts the print's ink prior when the current
    /// calibration learnt one, or a calibration job running or queued ahead may learn one.
    #[serde(default)]
    pub memory_mb: u64,
    /// `resume_session`: the session resumed and the first frame this job takes (the
    /// frames before it are that session's; `total_frames` counts the whole plan).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub resumed_from: Option<crate::session::ResumedFrom>,
    /// What the job will do other than asked, though it runs (a step the axis' motor
    /// cannot make exactly, and the moves it makes instead).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub warnings: Vec<String>,
}

/// `status` without a job id: the daemon's.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct DaemonStatus {
    pub running: Option<JobStatus>,
    pub queued: Vec<u64>,
    /// The queued jobs' statuses in queue order, with their expected start and ETA.
    #[serde(default)]
    pub queued_jobs: Vec<JobStatus>,
    pub shutting_down: bool,
    #[serde(default)]
    pub rig_state: RigState,
}

/// The reply to `unlock`, `home`, `reconnect`: what the controller reports after it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct RigActionReply {
    pub request: RigAction,
    pub stage: StageKind,
    pub state: MotionState,
    pub position_um: f64,
    pub rig_state: RigState,
}

/// A session on disk, as `list` shows it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct SessionSummary {
    pub name: String,
    pub job_id: u64,
    pub state: SessionState,
    pub reason: Option<String>,
    pub frames_captured: usize,
    pub total_frames: u32,
    pub replay_of: Option<String>,
    /// The session this one resumes, and the plan index of its own first frame.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub resumed_from: Option<crate::session::ResumedFrom>,
    pub label: Option<String>,
    /// started_at, ended_at, elapsed_s (from the manifest's times).
    #[serde(flatten)]
    pub timing: crate::daemon::timing::JobTiming,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct ListReply {
    pub jobs: Vec<JobStatus>,
    pub sessions: Vec<SessionSummary>,
    /// Set when older jobs or sessions are left out: ask again with `before` this.
    pub next_before: Option<u64>,
}

/// A queued job is cancelled at once; a running one is told to stop.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum CancelState {
    Cancelled,
    Cancelling,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct CancelReply {
    pub job_id: u64,
    pub state: CancelState,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct ResultReply {
    pub job_id: u64,
    pub session: String,
    pub state: SessionState,
    pub reason: Option<String>,
    /// The session's `result.json`, as recorded (`JobResult`).
    #[schemars(with = "Option<crate::acquisition::study::JobResult>")]
    pub result: Option<serde_json::Value>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct SubscribeReply {
    pub subscribed: Option<u64>,
    pub status: Option<JobStatus>,
}

/// The `result` of an ok reply, one shape per request.
#[derive(Debug, Clone, PartialEq, Serialize, schemars::JsonSchema)]
#[serde(untagged)]
pub enum ReplyBody {
    Hello(HelloReply),
    Submit(SubmitReply),
    DaemonStatus(DaemonStatus),
    JobStatus(JobStatus),
    List(ListReply),
    Cancel(CancelReply),
    Result(ResultReply),
    Subscribe(SubscribeReply),
    RigAction(RigActionReply),
    Snap(Box<SnapReply>),
    Preview(PreviewReply),
    PreviewStop(PreviewStopReply),
    Position(crate::daemon::manual::PositionReply),
    Move(crate::daemon::manual::MoveReply),
    Stop(crate::daemon::manual::StopReply),
    Pause(crate::daemon::pausing::PauseReply),
}

impl Reply {
    /// An ok reply carrying `body`.
    pub fn with(id: Option<serde_json::Value>, body: &ReplyBody) -> Reply {
        Reply::ok(
            id,
            serde_json::to_value(body).expect("replies are plain data"),
        )
    }
}

/// Encode a server line as JSON + newline.
pub fn encode(line: &ServerLine) -> Vec<u8> {
    let mut v = serde_json::to_vec(line).expect("server lines are plain data");
    v.push(b'\n');
    v
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::acquisition::JobRegistration;
    use crate::pipeline::Registration;

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
    fn the_protocol_is_strict_on_every_request() {
        let refused = |line: &[u8]| decode_request(line).unwrap_err().1;
        // Unknown fields on the requests with none or optional ones.
        for line in [
            &br#"{"kind":"hello","x":1}"#[..],
            br#"{"kind":"list","lmit":5}"#,
            br#"{"kind":"subscribe","job":1}"#,
        ] {
            let e = refused(line);
            assert_eq!(e.code, ErrorCode::BadRequest, "{e:?}");
            assert!(e.message.contains("unknown field"), "{}", e.message);
        }
        // A job as an array of its fields in order, which serde alone would take.
        let e = refused(br#"{"kind":"submit","job":["axis",50,3]}"#);
        assert_eq!(e.message, "`job` must be a JSON object, got an array");
        let e = refused(br#"{"kind":"replay","session":"s","processing":[10]}"#);
        assert!(e.message.starts_with("`processing` must be a JSON object"));
        // Duplicate keys, at the top and inside the job: the last would have won.
        let e = refused(br#"{"kind":"submit","job":{"steps":3,"step_um":5,"steps":3000}}"#);
        assert_eq!(e.code, ErrorCode::BadRequest);
        assert!(
            e.message.starts_with(r#"duplicate key "steps" in `job`"#),
            "{}",
            e.message
        );
        let e = refused(br#"{"id":1,"id":2,"kind":"hello"}"#);
        assert!(e.message.contains(r#"duplicate key "id""#), "{}", e.message);
        // Ids: strings and integers within ±(2^53 - 1) come back; others are refused.
        for id in ["9007199254740991", "-9007199254740991", "0", "\"x\""] {
            let line = format!(r#"{{"id":{id},"kind":"hello"}}"#);
            let e = decode_request(line.as_bytes()).unwrap();
            assert_eq!(e.id.unwrap().to_string(), id.replace('\\', ""));
        }
        for id in [
            "9007199254740992",
            "18446744073709551616",
            "1.5",
            "1e3",
            "true",
            "[1]",
        ] {
            let line = format!(r#"{{"id":{id},"kind":"hello"}}"#);
            let (back, e) = decode_request(line.as_bytes()).unwrap_err();
            assert_eq!((back, e.code), (None, ErrorCode::BadRequest), "{id}");
            assert!(
                e.message
                    .starts_with("`id` must be a string or an integer within ±9007199254740991"),
                "{}",
                e.message
            );
        }
        // The strict requests still decode.
        assert_eq!(
            decode_request(br#"{"kind":"list","limit":5,"before":40}"#)
                .unwrap()
                .request,
            Request::List {
                limit: Some(5),
                before: Some(40)
            }
        );
        assert_eq!(
            decode_request(br#"{"kind":"hello"}"#).unwrap().request,
            Request::Hello {}
        );
    }

    #[test]
    fn events_round_trip_with_the_job_id() {
        let ev = ServerLine::Event(Event {
            v: 1,
            job_id: 4,
            body: EventBody::Cancelled {
                session: None,
                reason: None,
                detail: None,
            },
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
                },
                total_frames: 1,
                piezo_commanded_um: None,
                piezo_um: None,
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
