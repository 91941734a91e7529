//! rigd-sim: the virtual rig rigd is tested, demonstrated and replayed against.
//!
//! It shares no parsing code with rigd's drivers: the controller emulators speak the real
//! serial protocols on pseudo-terminals, and the XL-80 synthesizer writes the real file
//! formats, so a driver test against them is not circular.

pub mod camera;
pub mod camera_clock;
pub mod crb;
pub mod frames;
pub mod gcs;
pub mod grbl;
pub mod isp;
pub mod light;
pub mod motion;
pub mod optics;
pub mod print;
pub mod pty;
pub mod render;
pub mod rig;
pub mod serve;
pub mod warp;
pub mod xl80;

// The boards live in rigd-core (the pipeline reads them too); `rigd_sim::board` stays a path.
pub use camera::CameraModel;
pub use camera_clock::{FrameClockCamera, SimFrame};
pub use frames::FrameRenderer;
pub use render::{SceneRenderer, View};
pub use rig::{SimRig, SimRigConfig};
pub use rigd_core::board;
pub use rigd_core::board::Board;
