//! `rigctl info` (or `hello`): what rig the daemon runs, from its `hello` reply — what a
//! user checks before trusting a number: the scale, the frame, the limits, the axis
//! controller's own settings, where sessions go, and the versions.

use crate::cli::client::SocketArg;
use crate::daemon::protocol::{HelloReply, Request};
use crate::text::{num, wire_name};

#[derive(clap::Args, Debug)]
pub struct InfoArgs {
    #[command(flatten)]
    pub socket: SocketArg,
    /// Print the daemon's `hello` reply as JSON.
    #[arg(long)]
    pub json: bool,
}

pub fn run(a: InfoArgs) -> anyhow::Result<()> {
    let mut c = a.socket.connect()?;
    let v = c.request(&Request::Hello {})?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&v)?);
        return Ok(());
    }
    let h: HelloReply = serde_json::from_value(v)?;
    print!("{}", describe(&h));
    Ok(())
}

/// The reply as lines of `name: value`.
pub fn describe(h: &HelloReply) -> String {
    let r = &h.rig;
    let mut lines = vec![
        ("rig", wire_name(&r.mode)),
        ("state", crate::cli::rig::describe(&h.rig_state)),
        ("scale", format!("{} µm/px", num(r.scale_um_per_px))),
        (
            "frame",
            format!("{} x {} px", r.frame_size.0, r.frame_size.1),
        ),
        ("axis limits", span(r.axis_limits_um)),
        (
            "piezo limits",
            r.piezo_limits_um.map_or("no piezo".into(), span),
        ),
        ("default start", format!("{} µm", num(r.default_start_um))),
    ];
    if let Some(c) = &r.camera {
        lines.push(("camera", c.clone()));
    }
    if let Some(m) = &r.axis_machine {
        lines.push((
            "axis controller",
            format!(
                "{}: motor step {} µm, top speed {} µm/s, acceleration {} µm/s²",
                m.controller,
                num(m.motor_step_um),
                num(m.max_rate_um_s),
                num(m.accel_um_s2)
            ),
        ));
    }
    lines.extend([
        ("data root", h.data_root.display().to_string()),
        ("rigd", format!("{} (protocol {})", h.rigd, h.protocol)),
    ]);
    let width = lines.iter().map(|(k, _)| k.len()).max().unwrap_or(0);
    lines
        .iter()
        .map(|(k, v)| format!("{k:width$}  {v}\n"))
        .collect()
}

fn span([lo, hi]: [f64; 2]) -> String {
    format!("{} to {} µm", num(lo), num(hi))
}
