//! rigd-core: the pure core of rigd, shared by the daemon and the simulator.
//!
//! - `board`: target boards (`config/boards/*.toml`), what is printed where, in micrometres.
//! - `pipeline`: frames + positions -> measured target offsets (the science).
//!
//! Nothing here knows of hardware, sessions, the wire protocol or JSON: frames come in as
//! decoded images with their positions, results go out as plain data.

pub mod board;
pub mod calibration;
pub mod pipeline;

pub use board::Board;
