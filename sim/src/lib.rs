//! rigd-sim: the virtual rig rigd is tested, demonstrated and replayed against.
//!
//! It shares no parsing code with rigd's drivers: the controller emulators speak the real
//! serial protocols on pseudo-terminals, and the XL-80 synthesizer writes the real file
//! formats, so a driver test against them is not circular.

pub mod board;
pub mod camera;
pub mod crb;
pub mod motion;
pub mod render;

pub use board::Board;
pub use camera::CameraModel;
pub use render::View;
