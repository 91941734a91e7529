//! `rigctl reprocess SESSION... [processing flags]`: many sessions processed again without
//! a daemon, side by side, each result written inside its session under
//! `processed/<settings>/` and indexed (docs/reprocessing.md).

use crate::cli::process::ProcessingFlags;
use crate::offline::reprocess::{reprocess, Done, IndexTarget, Reprocess};
use std::io::BufRead;
use std::path::PathBuf;

#[derive(clap::Args)]
#[command(
    after_help = "Each session's runs are processed as the daemon processed them (its \
                  manifest's board, scale, directions, runs and recorded options); the flags \
                  given override those options for every run and name the results' folder: \
                  processed/<settings>/ (`recorded` without flags, else e.g. \
                  fit-interp-k10-image), holding result.json, settings.json and images/. \
                  Frames are read where they are; nothing else in the session changes."
)]
pub struct ReprocessArgs {
    /// Session folders (each holding manifest.json).
    #[arg(value_name = "SESSION")]
    pub sessions: Vec<PathBuf>,
    /// Read more session folders from this file, one per line ("-": standard input).
    #[arg(long, value_name = "FILE")]
    pub from: Option<PathBuf>,
    #[command(flatten)]
    pub flags: ProcessingFlags,
    /// Board file overriding each session's rig board.
    #[arg(long)]
    pub board: Option<PathBuf>,
    /// Sessions processed at once [default: the cores rigctl may use].
    #[arg(long, value_name = "N")]
    pub threads: Option<usize>,
    /// Add the rows to this index instead of <data root>/index.sqlite (each session's
    /// parent folder's): a cluster task's own index, merged later (`rigctl index merge`).
    #[arg(long, value_name = "FILE", conflicts_with = "no_index")]
    pub index: Option<PathBuf>,
    /// Index nothing.
    #[arg(long)]
    pub no_index: bool,
}

pub fn run(a: ReprocessArgs) -> anyhow::Result<()> {
    let mut sessions = a.sessions.clone();
    if let Some(list) = &a.from {
        sessions.extend(read_list(list)?);
    }
    if sessions.is_empty() {
        anyhow::bail!("no session given (SESSION... or --from FILE)");
    }
    let board = match &a.board {
        Some(p) => Some(crate::board::Board::load(p)?),
        None => None,
    };
    let threads = a
        .threads
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    let how = Reprocess {
        overrides: a.flags.overrides(),
        board,
        calibration: a.flags.calibration()?,
        no_calibration: a.flags.no_calibration,
        threads,
        index: match (&a.index, a.no_index) {
            (_, true) => IndexTarget::None,
            (Some(p), false) => IndexTarget::File(p.clone()),
            (None, false) => IndexTarget::DataRoot,
        },
    };
    let report = |d: &Done| match &d.outcome {
        Ok(s) => println!(
            "{}: {} runs ({} failed), {} rows -> {}",
            d.session.display(),
            s.runs,
            s.runs_failed,
            s.rows,
            s.out.display()
        ),
        Err(e) => eprintln!("{}: failed: {e}", d.session.display()),
    };
    let done = reprocess(&sessions, &how, &report)?;
    let failed: Vec<&Done> = done.iter().filter(|d| d.outcome.is_err()).collect();
    println!(
        "{} sessions reprocessed as {}, {} failed",
        done.len() - failed.len(),
        how.overrides.settings_name(),
        failed.len()
    );
    if !failed.is_empty() {
        let names: Vec<String> = failed
            .iter()
            .map(|d| d.session.display().to_string())
            .collect();
        anyhow::bail!("{} sessions failed: {}", failed.len(), names.join(", "));
    }
    Ok(())
}

/// Session folders listed one per line (blank lines and `#` comments skipped).
fn read_list(path: &std::path::Path) -> anyhow::Result<Vec<PathBuf>> {
    let read: Box<dyn BufRead> = match path.to_str() {
        Some("-") => Box::new(std::io::stdin().lock()),
        _ => Box::new(std::io::BufReader::new(std::fs::File::open(path).map_err(
            |e| anyhow::anyhow!("{}: cannot open: {e}", path.display()),
        )?)),
    };
    let mut out = Vec::new();
    for line in read.lines() {
        let line = line.map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
        let t = line.trim();
        if !t.is_empty() && !t.starts_with('#') {
            out.push(PathBuf::from(t));
        }
    }
    Ok(out)
}
