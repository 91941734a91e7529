//! The results index across sessions: one SQLite file (`<data root>/index.sqlite`), one row
//! per target measured in a run of a session processed with a set of settings. `rigctl
//! reprocess` and the daemon (when a job ends) add rows; `rigctl results` queries them as
//! CSV; `rigctl index rebuild` makes the file again from the sessions' result files, and
//! `rigctl index merge` joins the per-task indexes of a cluster job (docs/reprocessing.md).
//!
//! A session's rows for one settings name are replaced as a whole, in one transaction, so
//! processing a session again never doubles its rows. Writers wait for each other (a busy
//! timeout), so several processes may add to one index.

use crate::acquisition::study::JobResult;
use rusqlite::{params, Connection, OptionalExtension};
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::time::Duration;

/// The index's file name under a data root.
pub const INDEX_FILE: &str = "index.sqlite";
/// The settings name of the results a session's job itself produced (its `result.json`).
pub const RECORDED: &str = "recorded";

/// How long a writer waits for another's transaction before giving up.
const BUSY: Duration = Duration::from_secs(60);

const SCHEMA: &str = "
CREATE TABLE IF NOT EXISTS results (
    session    TEXT NOT NULL,
    run        INTEGER NOT NULL,
    \"case\"   TEXT NOT NULL,
    \"repeat\" INTEGER NOT NULL,
    target     TEXT NOT NULL,
    dx_um      REAL,
    dy_um      REAL,
    u_dx_um REAL,
    u_dy_um REAL,
    settings   TEXT NOT NULL,
    date       TEXT NOT NULL,
    label      TEXT,
    PRIMARY KEY (session, settings, run, target)
);
CREATE INDEX IF NOT EXISTS results_date ON results (date);
";

/// The columns, in order: the CSV's header and the table's.
pub const COLUMNS: [&str; 12] = [
    "session", "run", "case", "repeat", "target", "dx_um", "dy_um", "u_dx_um", "u_dy_um",
    "settings", "date", "label",
];

/// One target of one run. `date`: the session's start, RFC 3339 UTC (`2026-12-02T03:33:58Z`).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Row {
    pub session: String,
    pub run: u32,
    pub case: String,
    pub repeat: u32,
    pub target: String,
    pub dx_um: Option<f64>,
    pub dy_um: Option<f64>,
    pub u_dx_um: Option<f64>,
    pub u_dy_um: Option<f64>,
    pub settings: String,
    pub date: String,
    pub label: Option<String>,
}

/// Which rows a query returns (every field given must match; `since`: on or after).
#[derive(Debug, Clone, Default)]
pub struct Filter {
    pub since: Option<String>,
    pub label: Option<String>,
    pub target: Option<String>,
    pub settings: Option<String>,
}

#[derive(Debug, thiserror::Error)]
#[error("{}: {source}", path.display())]
pub struct IndexError {
    pub path: PathBuf,
    pub source: rusqlite::Error,
}

/// Why a rebuild failed: the new index, or putting it in place.
#[derive(Debug, thiserror::Error)]
pub enum RebuildError {
    #[error(transparent)]
    Index(#[from] IndexError),
    #[error("{}: cannot put the rebuilt index in place: {source}", path.display())]
    Rename {
        path: PathBuf,
        source: std::io::Error,
    },
}

/// What a session says of itself in every row.
#[derive(Debug, Clone)]
pub struct SessionFacts {
    pub session: String,
    pub date: String,
    pub label: Option<String>,
}

impl SessionFacts {
    /// The facts of a session read from its folder: filed under the folder's name (a copy
    /// of a session is its own session, whatever its manifest says it was called).
    pub fn of_session(s: &crate::session::Session) -> SessionFacts {
        let mut facts = SessionFacts::of(&s.manifest);
        if let Some(folder) = s.dir.file_name().and_then(|n| n.to_str()) {
            facts.session = folder.to_string();
        }
        facts
    }

    pub fn of(m: &crate::session::Manifest) -> SessionFacts {
        SessionFacts {
            session: m.name.clone(),
            date: crate::timestamps::rfc3339_unix(m.created_unix_s).unwrap_or_default(),
            label: m.job.label.clone(),
        }
    }
}

/// A result's rows: every target of every run that has a result (a target without a name,
/// no board, is `#N` by its place in the run).
pub fn rows_of(facts: &SessionFacts, settings: &str, result: &JobResult) -> Vec<Row> {
    let finite = |v: f64| v.is_finite().then_some(v);
    let mut rows = Vec::new();
    for r in &result.runs {
        let Some(res) = &r.result else { continue };
        for (i, o) in res.objects.iter().enumerate() {
            // As results.csv: the combined uncertainty, else (older results) sigma_um.
            let sigma = o.u_um.or(o.sigma_um).map(|s| s.map(finite));
            rows.push(Row {
                session: facts.session.clone(),
                run: r.run,
                case: r.case.clone(),
                repeat: r.repeat,
                target: o.name.clone().unwrap_or_else(|| format!("#{i}")),
                dx_um: finite(o.offset_um[0]),
                dy_um: finite(o.offset_um[1]),
                u_dx_um: sigma.and_then(|s| s[0]),
                u_dy_um: sigma.and_then(|s| s[1]),
                settings: settings.to_string(),
                date: facts.date.clone(),
                label: facts.label.clone(),
            });
        }
    }
    rows
}

/// Files or sessions left out, each with why.
pub type Skipped = Vec<(PathBuf, String)>;

/// An open index.
pub struct Index {
    path: PathBuf,
    conn: Connection,
}

impl Index {
    /// Open (or create) the index at `path`.
    pub fn open(path: &Path) -> Result<Index, IndexError> {
        let err = |source| IndexError {
            path: path.to_path_buf(),
            source,
        };
        // Never through a symlink planted in the data root.
        let flags = rusqlite::OpenFlags::default() | rusqlite::OpenFlags::SQLITE_OPEN_NOFOLLOW;
        let conn = Connection::open_with_flags(path, flags).map_err(err)?;
        conn.busy_timeout(BUSY).map_err(err)?;
        conn.execute_batch(SCHEMA).map_err(err)?;
        Ok(Index {
            path: path.to_path_buf(),
            conn,
        })
    }

    fn err(&self) -> impl Fn(rusqlite::Error) -> IndexError + '_ {
        |source| IndexError {
            path: self.path.clone(),
            source,
        }
    }

    /// Replace `session`'s rows for `settings` with `rows`, in one transaction.
    pub fn replace(
        &mut self,
        session: &str,
        settings: &str,
        rows: &[Row],
    ) -> Result<(), IndexError> {
        let path = self.path.clone();
        let err = |source| IndexError {
            path: path.clone(),
            source,
        };
        let tx = self.conn.transaction().map_err(err)?;
        tx.execute(
            "DELETE FROM results WHERE session = ?1 AND settings = ?2",
            params![session, settings],
        )
        .map_err(err)?;
        {
            let mut ins = tx
                .prepare_cached(
                    "INSERT OR REPLACE INTO results VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12)",
                )
                .map_err(err)?;
            for r in rows {
                ins.execute(params![
                    r.session, r.run, r.case, r.repeat, r.target, r.dx_um, r.dy_um, r.u_dx_um,
                    r.u_dy_um, r.settings, r.date, r.label
                ])
                .map_err(err)?;
            }
        }
        tx.commit().map_err(err)
    }

    /// The rows `f` selects, by date, session, settings, run and target.
    pub fn query(&self, f: &Filter) -> Result<Vec<Row>, IndexError> {
        let sql = "SELECT session, run, \"case\", \"repeat\", target, dx_um, dy_um, u_dx_um, \
                   u_dy_um, settings, date, label FROM results \
                   WHERE (?1 IS NULL OR date >= ?1) AND (?2 IS NULL OR label = ?2) \
                   AND (?3 IS NULL OR target = ?3) AND (?4 IS NULL OR settings = ?4) \
                   ORDER BY date, session, settings, run, target";
        let mut st = self.conn.prepare(sql).map_err(self.err())?;
        let rows = st
            .query_map(params![f.since, f.label, f.target, f.settings], |r| {
                Ok(Row {
                    session: r.get(0)?,
                    run: r.get(1)?,
                    case: r.get(2)?,
                    repeat: r.get(3)?,
                    target: r.get(4)?,
                    dx_um: r.get(5)?,
                    dy_um: r.get(6)?,
                    u_dx_um: r.get(7)?,
                    u_dy_um: r.get(8)?,
                    settings: r.get(9)?,
                    date: r.get(10)?,
                    label: r.get(11)?,
                })
            })
            .map_err(self.err())?;
        rows.collect::<Result<Vec<_>, _>>().map_err(self.err())
    }

    /// Add every row of the index at `other` (rows of the same session, settings, run and
    /// target are replaced). Returns how many rows it held.
    pub fn merge_from(&mut self, other: &Path) -> Result<usize, IndexError> {
        let oerr = |source| IndexError {
            path: other.to_path_buf(),
            source,
        };
        // Opened on its own first: a file that is not an index is named as such.
        let o = Connection::open_with_flags(other, rusqlite::OpenFlags::SQLITE_OPEN_READ_ONLY)
            .map_err(oerr)?;
        let n: Option<usize> = o
            .query_row("SELECT count(*) FROM results", [], |r| r.get(0))
            .optional()
            .map_err(oerr)?;
        drop(o);
        // ATTACH is refused inside a transaction: attach, copy in one, detach.
        self.conn
            .execute(
                "ATTACH DATABASE ?1 AS other",
                params![other.to_string_lossy()],
            )
            .map_err(oerr)?;
        let copied = self.conn.execute_batch(
            "BEGIN; INSERT OR REPLACE INTO results SELECT * FROM other.results; COMMIT;",
        );
        if copied.is_err() {
            let _ = self.conn.execute_batch("ROLLBACK;");
        }
        let detached = self.conn.execute("DETACH DATABASE other", []);
        copied.map_err(oerr)?;
        detached.map_err(oerr)?;
        Ok(n.unwrap_or(0))
    }
}

/// Rows as CSV (header [`COLUMNS`]; an absent value is an empty cell).
pub fn write_csv(rows: &[Row], out: impl std::io::Write) -> Result<(), csv::Error> {
    let mut w = csv::WriterBuilder::new()
        .has_headers(false)
        .from_writer(out);
    w.write_record(COLUMNS)?;
    for r in rows {
        w.serialize(r)?;
    }
    w.flush()?;
    Ok(())
}

/// Every result file of the session in `dir`: its own `result.json` (settings
/// [`RECORDED`]) and each `processed/<settings>/result.json`, as rows. Files that cannot be
/// read are returned with why.
pub fn session_rows(s: &crate::session::Session) -> (Vec<(String, Vec<Row>)>, Skipped) {
    let facts = SessionFacts::of_session(s);
    let mut out = Vec::new();
    let mut bad = Vec::new();
    let mut files = vec![(RECORDED.to_string(), PathBuf::from(crate::session::RESULT))];
    let processed = s.dir.join(super::outputs::PROCESSED);
    if let Ok(rd) = std::fs::read_dir(&processed) {
        let mut names: Vec<String> = rd
            .flatten()
            .filter(|e| e.file_type().is_ok_and(|t| t.is_dir()))
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        for n in names {
            let rel = Path::new(super::outputs::PROCESSED)
                .join(&n)
                .join("result.json");
            files.push((n, rel));
        }
    }
    for (settings, rel) in files {
        let bytes = match crate::nofollow::read_in_max(&s.dir, &rel, crate::bounds::MAX_STEPS_BYTES)
        {
            Ok(b) => b,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => continue,
            Err(e) => {
                bad.push((s.dir.join(&rel), e.to_string()));
                continue;
            }
        };
        match serde_json::from_slice::<JobResult>(&bytes) {
            Ok(r) => out.push((settings.clone(), rows_of(&facts, &settings, &r))),
            Err(e) => bad.push((s.dir.join(&rel), format!("not a result: {e}"))),
        }
    }
    (out, bad)
}

/// Make the index at `into` again from every session under `data_root`: written to a
/// temporary file and renamed over `into`, so readers see the old index or the new one.
/// Returns the sessions indexed, the rows, and what was skipped with why.
pub fn rebuild(data_root: &Path, into: &Path) -> Result<(usize, usize, Skipped), RebuildError> {
    let tmp = into.with_file_name(format!(
        ".{}.tmp",
        into.file_name()
            .map_or("index".into(), |n| n.to_string_lossy())
    ));
    let _ = std::fs::remove_file(&tmp);
    let mut index = Index::open(&tmp)?;
    let (sessions, mut skipped) = crate::session::scan(data_root);
    let mut rows = 0;
    for s in &sessions {
        let (files, bad) = session_rows(s);
        skipped.extend(bad);
        for (settings, r) in files {
            rows += r.len();
            index.replace(&s.manifest.name, &settings, &r)?;
        }
    }
    drop(index);
    std::fs::rename(&tmp, into).map_err(|source| RebuildError::Rename {
        path: into.to_path_buf(),
        source,
    })?;
    Ok((sessions.len(), rows, skipped))
}
