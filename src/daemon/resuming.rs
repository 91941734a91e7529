//! Resuming an interrupted session (`resume_session`): a new job with the session's job and
//! plan, checked against this rig as any job is, that takes the frames from the session's
//! first missing one on. The frames before it stay where they are (the original is never
//! written to) and are processed with the new ones: each run's result comes from all of its
//! frames, in plan order.
//!
//! A frame is kept when it has its `steps.csv` row (a complete one), its PNG is a regular
//! file in the session's `frames/` (and the last one decodes: a frame cut short counts as
//! missing), and the rows so far are the plan's indices in order; the first frame that fails
//! any of this is the first missing one. Every kept PNG must also be of the rig's frame size
//! and end whole (its header and trailer are read): one that is not is retaken. A resumed
//! session can be resumed again: its frames before its own first one are its original's,
//! found through `resumed_from`, the chain walked without recursion, at most 64 links, each
//! session once, one session's steps in memory at a time.

use crate::acquisition::job::JobRegistration;
use crate::acquisition::plan::{expand, Plan, RunPlan};
use crate::acquisition::processor::{Prior, PriorFrame};
use crate::acquisition::JobSpec;
use crate::bounds;
use crate::hw::devices::StageMachine;
use crate::nofollow::{self, Access};
use crate::rig::{RigInfo, RigMode};
use crate::session::{frame_name, ResumedFrom, Session, SessionState, StepRow, MANIFEST};
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// How many `resumed_from` links a chain of resumed sessions may have.
const MAX_CHAIN: usize = 64;

/// Why a session cannot be resumed (the wire's `not_found` or `rejected`).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ResumeError {
    #[error("{0}")]
    NotFound(String),
    #[error("{0}")]
    Rejected(String),
}

fn rejected(msg: impl Into<String>) -> ResumeError {
    ResumeError::Rejected(msg.into())
}

/// The frames a resumed job does not take, and where they are.
#[derive(Debug, Clone)]
pub struct Origin {
    pub link: ResumedFrom,
    /// The session folders holding the frames before `link.first_index`: each with the
    /// first plan index after its frames, in index order (a chain's oldest first).
    pub folders: Vec<(u32, PathBuf)>,
    /// Those frames, in plan order (index 0 up to `link.first_index`).
    pub frames: Vec<PriorFrame>,
    /// Their size: the rig's (the recorded one, checked).
    pub frame_size: (u32, u32),
}

impl Origin {
    /// The earlier frames as processing reads them: through `nofollow`, from the folder
    /// that holds each.
    pub fn prior(&self) -> Prior {
        let folders = self.folders.clone();
        let size = self.frame_size;
        Prior {
            frames: self.frames.clone(),
            load: Box::new(move |index| {
                let dir = folders
                    .iter()
                    .find(|(end, _)| index < *end)
                    .map(|(_, d)| d)
                    .ok_or_else(|| format!("frame {index} is in no earlier session"))?;
                read_frame(dir, index, size)
            }),
        }
    }
}

/// The job to resume session `dir` with on `rig`: the recorded job, its plan as this rig
/// expands it (which must be the recorded one), starting at the first missing frame.
pub fn resume_job(
    data_root: &Path,
    dir: &Path,
    rig: &RigInfo,
) -> Result<(JobSpec, Plan, Origin), ResumeError> {
    let s = open(dir)?;
    // The link names the folder (what `list` shows and clients pass).
    let name = dir
        .file_name()
        .unwrap_or_default()
        .to_string_lossy()
        .into_owned();
    check_state(&s)?;
    check_rig(&s, rig)?;
    let spec = s.manifest.job.clone();
    // The plan as this rig expands it (bounded as any job's) before any frame is read.
    let mut plan = expand(&spec, rig)
        .map_err(|e| rejected(format!("session {name} cannot run on this rig: {e}")))?;
    same_positions(&name, &s.manifest.plan.runs, &plan.runs)?;
    let total_frames = s.manifest.plan.total_frames;
    drop(s);
    let kept = kept_frames(data_root, dir, rig.frame_size)?;
    let first_index = kept.len() as u32;
    if first_index >= total_frames {
        return Err(rejected(format!(
            "session {name} holds every frame of its plan ({total_frames}): nothing to resume \
             (replay it to process it again)"
        )));
    }
    plan.first_index = first_index;
    let registration = spec.registration.unwrap_or_default();
    let mut folders: Vec<(u32, PathBuf)> = Vec::new();
    let mut frames = Vec::with_capacity(kept.len());
    for (dir, row) in kept {
        match folders.last_mut() {
            Some((end, d)) if d.as_path() == &*dir => *end = row.index + 1,
            _ => folders.push((row.index + 1, dir.to_path_buf())),
        }
        frames.push(prior_frame(&row, registration, rig.axis_machine.as_ref()));
    }
    let link = ResumedFrom {
        session: name,
        first_index,
    };
    Ok((
        spec,
        plan,
        Origin {
            link,
            folders,
            frames,
            frame_size: rig.frame_size,
        },
    ))
}

fn open(dir: &Path) -> Result<Session, ResumeError> {
    let name = dir.file_name().unwrap_or_default().to_string_lossy();
    Session::open(dir).map_err(|e| rejected(format!("session {name} cannot be read: {e}")))
}

fn check_state(s: &Session) -> Result<(), ResumeError> {
    let m = &s.manifest;
    let name = &m.name;
    if m.replay_of.is_some() || m.rig.mode == RigMode::Replay {
        return Err(rejected(format!(
            "session {name} is a replay: replay its original again instead"
        )));
    }
    match m.state {
        SessionState::Incomplete | SessionState::Failed | SessionState::Cancelled => Ok(()),
        SessionState::Finished => Err(rejected(format!(
            "session {name} finished: nothing to resume (only an incomplete, failed or \
             cancelled session is resumed)"
        ))),
        SessionState::Running => Err(rejected(format!(
            "session {name} is running (job {}): cancel it first, then resume it",
            m.job_id
        ))),
    }
}

/// The rig must be the one the session was recorded on, as far as the frames' meaning
/// goes: the same mode, scale, frame size, stage directions and board.
fn check_rig(s: &Session, rig: &RigInfo) -> Result<(), ResumeError> {
    let was = &s.manifest.rig;
    let name = &s.manifest.name;
    let differs = |what: &str, then: String, now: String| {
        rejected(format!(
            "session {name} was recorded on another rig: its {what} was {then}, this rig's is \
             {now}"
        ))
    };
    if was.mode != rig.mode {
        return Err(differs("mode", text(&was.mode), text(&rig.mode)));
    }
    if was.scale_um_per_px != rig.scale_um_per_px {
        let um = |v: f64| format!("{v} µm/px");
        return Err(differs(
            "scale",
            um(was.scale_um_per_px),
            um(rig.scale_um_per_px),
        ));
    }
    if was.frame_size != rig.frame_size {
        let px = |(w, h): (u32, u32)| format!("{w}x{h} px");
        return Err(differs(
            "frame size",
            px(was.frame_size),
            px(rig.frame_size),
        ));
    }
    if was.axis_dir != rig.axis_dir || was.piezo_dir != rig.piezo_dir {
        return Err(differs(
            "stage directions (axis, piezo)",
            text(&(was.axis_dir, was.piezo_dir)),
            text(&(rig.axis_dir, rig.piezo_dir)),
        ));
    }
    if was.board != rig.board {
        let board = |b: &Option<crate::board::Board>| match b {
            Some(b) => format!("{:?}", b.name),
            None => "none".into(),
        };
        return Err(differs("board", board(&was.board), board(&rig.board)));
    }
    Ok(())
}

/// A value as the manifest writes it.
fn text<T: serde::Serialize>(v: &T) -> String {
    serde_json::to_string(v).unwrap_or_default()
}

/// This rig expands the recorded job into the recorded positions, or the resumed frames
/// would not continue the same plan (another default start, say).
fn same_positions(name: &str, was: &[RunPlan], now: &[RunPlan]) -> Result<(), ResumeError> {
    let differ = |what: String| {
        Err(rejected(format!(
            "session {name}'s job plans {what} on this rig than it recorded: not the same plan"
        )))
    };
    if was.len() != now.len() {
        return differ(format!("{} runs rather than {}", now.len(), was.len()));
    }
    for (a, b) in was.iter().zip(now) {
        let frame = a
            .positions_um
            .iter()
            .zip(&b.positions_um)
            .position(|(x, y)| x != y);
        if let Some(i) = frame {
            return differ(format!(
                "other positions (run {}, frame {i}: {} µm rather than {} µm)",
                a.run, b.positions_um[i], a.positions_um[i]
            ));
        }
        if a.positions_um.len() != b.positions_um.len() || a.piezo_um != b.piezo_um {
            return differ(format!("other frames in run {}", a.run));
        }
    }
    Ok(())
}

/// A kept frame: the folder holding it (shared by its session's frames) and its row.
type Kept = (Arc<Path>, StepRow);

/// The frames of the plan that the session in `dir` (and the sessions it resumed) hold,
/// from index 0 up to the first missing one: each with the folder holding it. The chain is
/// walked back by manifests alone (at most [`MAX_CHAIN`] links, each folder once), then
/// forward from its oldest session, one session's steps in memory at a time.
fn kept_frames(data_root: &Path, dir: &Path, size: (u32, u32)) -> Result<Vec<Kept>, ResumeError> {
    let chain = chain_of(data_root, dir)?;
    let mut kept: Vec<Kept> = Vec::new();
    for (dir, first) in chain.into_iter().rev() {
        kept.truncate(first as usize);
        if kept.len() < first as usize {
            // The original lost frames since: this session does not continue what is there.
            return Ok(kept);
        }
        let s = open(&dir)?;
        keep_frames_of(&s, &mut kept, size);
    }
    Ok(kept)
}

/// The folders of the chain that ends at `dir`, newest first, each with its plan's first
/// index (0 for the chain's original).
fn chain_of(data_root: &Path, dir: &Path) -> Result<Vec<(PathBuf, u32)>, ResumeError> {
    let mut chain: Vec<(PathBuf, u32)> = Vec::new();
    let mut at = dir.to_path_buf();
    loop {
        let m = manifest(&at)?;
        let first = m.plan.first_index;
        chain.push((at.clone(), first));
        let link = match (&m.resumed_from, first) {
            (_, 0) => return Ok(chain),
            (None, _) => {
                return Err(rejected(format!(
                    "session {} starts at frame {first} and names no session it resumes",
                    m.name
                )))
            }
            (Some(link), _) => link,
        };
        if chain.len() > MAX_CHAIN {
            return Err(rejected(format!(
                "session {} resumes a chain of more than {MAX_CHAIN} sessions",
                m.name
            )));
        }
        let next = linked_dir(data_root, &m.name, &link.session)?;
        if chain.iter().any(|(d, _)| *d == next) {
            return Err(rejected(format!(
                "session {} resumes session {}, which is already in its chain of resumed \
                 sessions: a cycle",
                m.name, link.session
            )));
        }
        at = next;
    }
}

/// The manifest of the session in `dir` (its steps not read).
fn manifest(dir: &Path) -> Result<crate::session::Manifest, ResumeError> {
    let name = dir.file_name().unwrap_or_default().to_string_lossy();
    Session::read_manifest(dir).map_err(|e| rejected(format!("session {name} cannot be read: {e}")))
}

/// Append to `kept` the frames of `s` that continue it in plan order, each with its row, an
/// intact PNG of the rig's frame `size` in `s`'s `frames/`; the last one is decoded too.
fn keep_frames_of(s: &Session, kept: &mut Vec<Kept>, size: (u32, u32)) {
    let plan: Vec<f64> = s
        .manifest
        .plan
        .runs
        .iter()
        .flat_map(|r| r.positions_um.iter().copied())
        .collect();
    let here: Arc<Path> = Arc::from(s.dir.as_path());
    let before = kept.len();
    for row in &s.steps {
        let i = kept.len();
        let planned = plan.get(i).copied();
        if row.index as usize != i || planned != Some(row.position_um) {
            break;
        }
        if !frame_intact(&s.dir, i, size) {
            break;
        }
        kept.push((here.clone(), row.clone()));
    }
    // A frame cut short inside (written by other means than rigd's, which renames whole
    // files into place) counts as missing: the last one is decoded whole.
    if kept.len() > before {
        let last = kept.len() as u32 - 1;
        if read_frame(&s.dir, last, size).is_err() {
            kept.pop();
        }
    }
}

/// The folder of session `name` that `of` resumes, confined to the data root.
fn linked_dir(data_root: &Path, of: &str, name: &str) -> Result<PathBuf, ResumeError> {
    let dir = data_root.join(name);
    let bad = bounds::one_component("session", name).is_err();
    if bad || !dir.join(MANIFEST).is_file() {
        return Err(ResumeError::NotFound(format!(
            "session {of} resumes session {name:?}, which is not in the data root"
        )));
    }
    Ok(dir)
}

/// The PNG trailer every whole file ends with: the empty `IEND` chunk and its CRC.
const IEND: [u8; 12] = [0, 0, 0, 0, b'I', b'E', b'N', b'D', 0xAE, 0x42, 0x60, 0x82];

/// Frame `index`'s PNG is a regular file in `dir/frames` (not through a symlink) within the
/// size bound, its header says the rig's frame `size`, and it ends whole (`IEND`): a frame
/// of another size, or cut short, is retaken. Reads its first and last bytes only.
fn frame_intact(dir: &Path, index: usize, size: (u32, u32)) -> bool {
    use std::io::{Read, Seek, SeekFrom};
    let rel = Path::new("frames").join(frame_name(index as u32));
    let Ok(mut f) = nofollow::open_in(dir, &rel, Access::Read) else {
        return false;
    };
    let len = f.metadata().map(|m| m.len()).unwrap_or(0);
    let mut head = [0u8; 24];
    let mut tail = [0u8; 12];
    let read = (24 + 12..=bounds::MAX_FRAME_BYTES).contains(&len)
        && f.read_exact(&mut head).is_ok()
        && f.seek(SeekFrom::End(-12)).is_ok()
        && f.read_exact(&mut tail).is_ok();
    // Signature (8), IHDR length and type (8), then width and height, big-endian.
    let be = |b: &[u8]| u32::from_be_bytes([b[0], b[1], b[2], b[3]]);
    read && &head[12..16] == b"IHDR"
        && (be(&head[16..20]), be(&head[20..24])) == size
        && tail == IEND
}

/// Frame `index` of the session in `dir`, read through `nofollow` (bounded) and decoded;
/// it must be `size` (the rig's frame size).
pub fn read_frame(dir: &Path, index: u32, size: (u32, u32)) -> Result<image::RgbImage, String> {
    let rel = Path::new("frames").join(frame_name(index));
    let path = dir.join(&rel);
    let bytes = nofollow::read_in_max(dir, &rel, bounds::MAX_FRAME_BYTES)
        .map_err(|e| format!("{}: {e}", path.display()))?;
    bounds::decode_frame(&bytes, Some(size)).map_err(|e| format!("{}: {e}", path.display()))
}

/// A kept frame as processing takes it: registered as the live job would have.
fn prior_frame(
    row: &StepRow,
    registration: JobRegistration,
    machine: Option<&StageMachine>,
) -> PriorFrame {
    PriorFrame {
        index: row.index,
        run: row.run,
        registration_um: match registration {
            JobRegistration::Interferometer => row.interferometer_um,
            _ => Some(row.commanded_registration_um(machine)),
        },
        piezo_commanded_um: row.piezo_commanded_um,
    }
}
