//! rigd: a rig-control and acquisition daemon for offset-image averaging metrology.
//!
//! The map of the code is `docs/architecture.md`. In short:
//! - `acquisition`: the job, its plan (every check before anything moves), the step engine.
//! - `pipeline`, `board`: frames + positions -> measured target offsets (the science), and
//!   the target boards; re-exported from the `rigd-core` crate.
//! - `folder`: the `rigctl process` folder contract (frames/*.png + steps.csv).
//! - `calibration_file`, `calibration_store`: calibration records on disk, and the ones a
//!   daemon keeps in its data root (`calibrations/<id>.json`, `current`).
//! - `atomic_file`: files written whole or not at all (temporary name, sync, rename).
//! - `nofollow`: opening files below a folder without following a symlink.
//! - `bounds`: the limits of what rigd reads: file sizes, frame dimensions, number ranges,
//!   names that become file names.
//! - `lock`: exclusive flock'd lock files that name their holder (one owner per resource).
//! - `report`: the paper's tables from repeated runs; `results_csv`: the flat results table
//!   beside every result.json; `plot` and `figures`: labelled charts (Figures 4, 5, residuals).
//! - `hw`: hardware drivers (GRBL axis, PI GCS piezo, V4L2 camera) and their options.
//! - `rig`: the device traits, `Rig`/`RigInfo`, and the rig builders (config, sim, replay).
//! - `xl80`: Renishaw XL-80 interferometer logs (CSV export, CARTO .rtx), following and alignment.
//! - `config`: the rig's TOML configuration.
//! - `daemon`: protocol, server, job runner, sessions, replay.
//! - `export`: sessions as OME-TIFF and OME-Zarr.
//! - `cli`: the `rigctl` subcommands; the binaries in `src/bin` are thin.

pub mod acquisition;
pub mod atomic_file;
pub mod bounds;
pub mod calibration_file;
pub mod calibration_note;
pub mod calibration_store;
pub mod cli;
pub mod config;
pub mod daemon;
pub mod export;
pub mod figures;
pub mod folder;
pub mod hw;
pub mod lock;
pub mod nofollow;
pub mod offline;
pub mod ownership;
pub mod plot;
pub mod report;
pub mod results_csv;
pub mod rig;
pub mod session;
pub mod text;
pub mod timestamps;
pub mod versions;
pub mod xl80;

/// The simulator (feature `sim`, on by default).
#[cfg(feature = "sim")]
pub use rigd_sim as sim;
// The board and the pipeline live in rigd-core; `crate::pipeline::...` stays a path.
pub use rigd_core::{board, calibration, pipeline};
