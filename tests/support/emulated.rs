//! A controller emulator from sim/ serving a simulated axis on a pseudo-terminal, behind a
//! stable link in a temporary folder: what the driver tests open through real `serialport`.

use rigd::hw::{HwError, Stage};
use rigd::sim::motion::{Axis, AxisParams};
use rigd::sim::serve::Faults;
use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// An emulator `S` for one axis, and driver options `O` pointing at its port.
pub struct Rig<S, O> {
    _dir: tempfile::TempDir,
    pub axis: Arc<Axis>,
    pub sim: S,
    pub opts: O,
}

impl<S, O> Rig<S, O> {
    /// Start an emulator on a new axis with `params`, behind the link `dir/name`; `opts`
    /// makes the driver's options for that port path.
    pub fn spawn(
        params: AxisParams,
        name: &str,
        spawn: impl FnOnce(Arc<Axis>, &Path) -> std::io::Result<S>,
        opts: impl FnOnce(&str) -> O,
    ) -> Rig<S, O> {
        let dir = tempfile::tempdir().unwrap();
        let axis = Arc::new(Axis::new(params));
        let link = dir.path().join(name);
        let sim = spawn(axis.clone(), &link).unwrap();
        let opts = opts(link.to_str().unwrap());
        Rig {
            _dir: dir,
            axis,
            sim,
            opts,
        }
    }

    /// Where the simulated axis really is now, µm.
    pub fn true_um(&self) -> f64 {
        self.axis.position_at(Instant::now())
    }
}

/// Pull the port out, and give the emulator time to close it.
pub fn unplug(faults: &Faults) {
    faults.vanish();
    std::thread::sleep(Duration::from_millis(30));
}

/// Plug it back in (a new pty behind the same link).
pub fn replug(faults: &Faults) {
    faults.restore();
    std::thread::sleep(Duration::from_millis(30));
}

/// A relative move and its settling; the settled position the driver reports.
pub fn step(s: &mut impl Stage, delta_um: f64, settle: Duration) -> Result<f64, HwError> {
    s.move_rel(delta_um)?;
    s.wait_settled(settle)
}

/// Mean time per step over `n` steps of `delta_um` (for the `#[ignore]`d studies).
pub fn time_per_step(s: &mut impl Stage, delta_um: f64, n: u32, settle: Duration) -> Duration {
    let t = Instant::now();
    for _ in 0..n {
        step(s, delta_um, settle).unwrap();
    }
    t.elapsed() / n
}
