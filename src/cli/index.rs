//! `rigctl results` (the results index queried to CSV) and `rigctl index rebuild|merge`
//! (docs/reprocessing.md).

use crate::offline::index::{self, Filter, Index, INDEX_FILE};
use std::path::PathBuf;

/// Where the index is: `--index FILE`, else `<data root>/index.sqlite`.
#[derive(clap::Args, Debug)]
pub struct IndexLocation {
    /// The data root whose index.sqlite to use.
    #[arg(long, value_name = "DIR", default_value = "rigd-sessions")]
    pub data_root: PathBuf,
    /// An index file instead (e.g. a merged one).
    #[arg(long, value_name = "FILE")]
    pub index: Option<PathBuf>,
}

impl IndexLocation {
    pub fn path(&self) -> PathBuf {
        self.index
            .clone()
            .unwrap_or_else(|| self.data_root.join(INDEX_FILE))
    }
}

#[derive(clap::Args, Debug)]
pub struct ResultsArgs {
    #[command(flatten)]
    pub at: IndexLocation,
    /// Sessions started on or after this date (UTC: 2026-12-01, or 2026-12-01T08:00:00Z).
    #[arg(long, value_name = "DATE", value_parser = parse_date)]
    pub since: Option<String>,
    /// Only sessions with this label (the job's --label).
    #[arg(long)]
    pub label: Option<String>,
    /// Only this target (its board name, or #N without a board).
    #[arg(long)]
    pub target: Option<String>,
    /// Only results of these settings (`recorded`: the job's own; else a processed/ name).
    #[arg(long)]
    pub settings: Option<String>,
}

/// A date as the index stores them (RFC 3339 UTC), or its leading part: compared as text.
fn parse_date(s: &str) -> Result<String, String> {
    let fmt = time::macros::format_description!("[year]-[month]-[day]");
    let day = s.get(..10).unwrap_or(s);
    time::Date::parse(day, fmt).map_err(|e| format!("`{s}`: not a date YYYY-MM-DD ({e})"))?;
    Ok(s.to_string())
}

pub fn results(a: ResultsArgs) -> anyhow::Result<()> {
    let path = a.at.path();
    if !path.exists() {
        anyhow::bail!(
            "{}: no index (rigctl reprocess writes one; rigctl index rebuild makes it from the sessions)",
            path.display()
        );
    }
    let idx = Index::open(&path)?;
    let rows = idx.query(&Filter {
        since: a.since,
        label: a.label,
        target: a.target,
        settings: a.settings,
    })?;
    index::write_csv(&rows, std::io::stdout().lock())?;
    Ok(())
}

#[derive(clap::Args, Debug)]
pub struct IndexArgs {
    #[command(subcommand)]
    pub action: IndexAction,
}

#[derive(clap::Subcommand, Debug)]
pub enum IndexAction {
    /// Make the index again from every session's result.json and processed/*/result.json.
    Rebuild(RebuildArgs),
    /// Add the rows of other indexes (e.g. a cluster job's per-task ones) into one.
    Merge(MergeArgs),
}

#[derive(clap::Args, Debug)]
pub struct RebuildArgs {
    /// The data root holding the sessions.
    #[arg(long, value_name = "DIR", default_value = "rigd-sessions")]
    pub data_root: PathBuf,
    /// Write this file instead of <data root>/index.sqlite.
    #[arg(long, value_name = "FILE")]
    pub into: Option<PathBuf>,
}

#[derive(clap::Args, Debug)]
pub struct MergeArgs {
    /// The indexes to add.
    #[arg(required = true, value_name = "INDEX")]
    pub from: Vec<PathBuf>,
    /// The index they are added to (created if missing).
    #[arg(long, value_name = "FILE")]
    pub into: PathBuf,
}

pub fn run(a: IndexArgs) -> anyhow::Result<()> {
    match a.action {
        IndexAction::Rebuild(r) => {
            let into = r.into.unwrap_or_else(|| r.data_root.join(INDEX_FILE));
            let (sessions, rows, skipped) = index::rebuild(&r.data_root, &into)?;
            for (path, why) in &skipped {
                eprintln!("{}: skipped: {why}", path.display());
            }
            println!("{}: {rows} rows from {sessions} sessions", into.display());
        }
        IndexAction::Merge(m) => {
            let mut into = Index::open(&m.into)?;
            let mut total = 0;
            for f in &m.from {
                if !f.is_file() {
                    anyhow::bail!("{}: no such index", f.display());
                }
                total += into.merge_from(f)?;
            }
            println!(
                "{}: {total} rows merged from {} indexes",
                m.into.display(),
                m.from.len()
            );
        }
    }
    Ok(())
}
