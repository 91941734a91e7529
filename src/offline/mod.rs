//! Processing without a daemon: `rigctl process` on a folder or a session, `rigctl
//! reprocess` across many sessions, and the results index (docs/reprocessing.md).
//!
//! | module | job |
//! |---|---|
//! | `calibrate` | a calibration fitted from a folder's scan (`rigctl calibrate DIR`, the daemon's calibration job) |
//! | `push` | frames on disk through one run's pipeline, decoded ahead on threads |
//! | `ahead` | which frame a decoder takes next, never too far ahead of the pipeline |
//! | `overrides` | the command line's processing settings and their folder name |
//! | `session_runs` | a session's runs processed as the daemon processed them |
//! | `outputs` | `processed/<settings>/` inside a session: `result.json`, `settings.json`, images |
//! | `reprocess` | many sessions on a rayon pool, failures reported per session |
//! | `index` | the SQLite results index: rows, queries, rebuild, merge |

mod ahead;
pub mod calibrate;
pub mod index;
pub mod outputs;
pub mod overrides;
pub mod push;
pub mod reprocess;
pub mod session_runs;

pub use overrides::Overrides;
