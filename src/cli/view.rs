//! `rigctl snap` and `rigctl view`: the live view in a terminal. `snap` asks for one fresh
//! frame; `view` follows a preview subscription, showing per target its name, centre, a
//! sharpness bar (scaled to the sharpest that target has been seen so far) and the numbers,
//! refreshed in place on a terminal (plain lines otherwise). Both keep the latest frame as
//! a PNG on disk, written atomically so an image viewer never reads half a file.

use crate::atomic_file;
use crate::cli::client::SocketArg;
use crate::daemon::protocol::{EventBody, Request};
use crate::daemon::protocol::{SnapReply, ViewFrame, ViewTarget, MAX_FPS, MIN_FPS};
use anyhow::{bail, Context};
use base64::Engine as _;
use std::collections::HashMap;
use std::io::{IsTerminal, Write};
use std::path::{Path, PathBuf};

/// What the frame shows: the scale and the crop.
#[derive(clap::Args, Debug, Clone)]
pub struct ShowArgs {
    /// Scale the image by this (0 < S <= 1; default 1 for snap, 0.5 for view).
    #[arg(long, value_name = "S")]
    pub scale: Option<f64>,
    /// Show only this region of the frame, in frame pixels: X,Y,WIDTH,HEIGHT.
    #[arg(long, value_name = "X,Y,W,H", value_parser = parse_crop)]
    pub crop: Option<[u32; 4]>,
}

#[derive(clap::Args, Debug)]
pub struct SnapArgs {
    #[command(flatten)]
    pub socket: SocketArg,
    #[command(flatten)]
    pub show: ShowArgs,
    /// Where to write the frame (PNG).
    #[arg(long, value_name = "FILE.png", default_value = "rigd-snap.png")]
    pub out: PathBuf,
    /// Print the reply as JSON (without the image) instead of the table.
    #[arg(long)]
    pub json: bool,
}

#[derive(clap::Args, Debug)]
pub struct ViewArgs {
    #[command(flatten)]
    pub socket: SocketArg,
    #[command(flatten)]
    pub show: ShowArgs,
    /// Frames a second, at most (the daemon never sends more; a slow terminal gets fewer).
    #[arg(long, value_name = "N", default_value_t = 5.0, value_parser = parse_fps)]
    pub fps: f64,
    /// Where to keep the latest frame (PNG, replaced atomically).
    #[arg(long, value_name = "FILE.png", default_value = "rigd-preview.png")]
    pub out: PathBuf,
    /// Stop after this many frames (default: until interrupted).
    #[arg(long, value_name = "N")]
    pub frames: Option<u64>,
}

/// `--fps`: the daemon's range, checked before anything is sent.
fn parse_fps(s: &str) -> Result<f64, String> {
    let v: f64 = s.parse().map_err(|_| format!("`{s}` is not a number"))?;
    if (MIN_FPS..=MAX_FPS).contains(&v) {
        Ok(v)
    } else {
        Err(format!("must be from {MIN_FPS} to {MAX_FPS}, got {s}"))
    }
}

fn parse_crop(s: &str) -> Result<[u32; 4], String> {
    let v: Vec<u32> = s
        .split(',')
        .map(|p| p.trim().parse::<u32>())
        .collect::<Result<_, _>>()
        .map_err(|_| format!("{s:?}: expected X,Y,WIDTH,HEIGHT in pixels, e.g. 100,50,640,360"))?;
    v.try_into()
        .map_err(|_| format!("{s:?}: expected four numbers X,Y,WIDTH,HEIGHT"))
}

pub fn snap(a: SnapArgs) -> anyhow::Result<()> {
    let mut c = a.socket.connect()?;
    let req = Request::Snap {
        scale: a.show.scale,
        crop: a.show.crop,
    };
    let mut reply: SnapReply = serde_json::from_value(c.request(&req)?)?;
    save_png(&a.out, &reply.frame)?;
    if a.json {
        reply.frame.png_base64.clear();
        println!("{}", serde_json::to_string_pretty(&reply)?);
        return Ok(());
    }
    let source = match (reply.job_id, reply.frame.index) {
        (Some(j), Some(i)) => format!("job {j}'s frame {i}"),
        _ => "a fresh frame".to_string(),
    };
    println!(
        "{source}: {}x{} at {}; {} -> {}",
        reply.frame.width,
        reply.frame.height,
        at(&reply.frame),
        positions(&reply.frame),
        a.out.display()
    );
    let mut best = HashMap::new();
    for line in target_lines(&reply.frame.targets, &mut best) {
        println!("{line}");
    }
    Ok(())
}

pub fn view(a: ViewArgs) -> anyhow::Result<()> {
    let mut c = a.socket.connect()?;
    let req = Request::Preview {
        max_fps: a.fps,
        scale: Some(a.show.scale.unwrap_or(0.5)),
        crop: a.show.crop,
    };
    c.request(&req)?;
    let tty = std::io::stdout().is_terminal();
    let mut best: HashMap<String, f64> = HashMap::new();
    let mut shown_lines = 0usize;
    let mut n = 0u64;
    while a.frames.is_none_or(|max| n < max) {
        let e = c.next_event()?;
        let EventBody::Preview(frame) = e.body else {
            continue;
        };
        n += 1;
        save_png(&a.out, &frame)?;
        let mut lines = vec![format!(
            "frame {} at {}{}; {} -> {}",
            frame.sequence,
            at(&frame),
            match (e.job_id, frame.index) {
                (0, _) | (_, None) => String::new(),
                (j, Some(i)) => format!(" (job {j}, frame {i})"),
            },
            positions(&frame),
            a.out.display()
        )];
        lines.extend(target_lines(&frame.targets, &mut best));
        let mut out = std::io::stdout().lock();
        if tty && shown_lines > 0 {
            // Back to the first line of the last frame, each line cleared.
            write!(out, "\x1b[{shown_lines}A")?;
        }
        for l in &lines {
            if tty {
                write!(out, "\x1b[2K")?;
            }
            writeln!(out, "{l}")?;
        }
        if tty {
            // Lines of a longer previous frame, cleared.
            for _ in lines.len()..shown_lines {
                writeln!(out, "\x1b[2K")?;
            }
            shown_lines = shown_lines.max(lines.len());
        }
        out.flush()?;
    }
    Ok(())
}

/// The frame's image into `path`, atomically.
fn save_png(path: &Path, f: &ViewFrame) -> anyhow::Result<()> {
    let png = base64::engine::general_purpose::STANDARD
        .decode(&f.png_base64)
        .context("the frame's image is not base64")?;
    if !png.starts_with(b"\x89PNG") {
        bail!("the frame's image is not a PNG");
    }
    atomic_file::write(path, &png).with_context(|| format!("writing {}", path.display()))
}

fn at(f: &ViewFrame) -> String {
    let t = time::OffsetDateTime::from_unix_timestamp_nanos((f.t_unix_s * 1e9) as i128)
        .unwrap_or(time::OffsetDateTime::UNIX_EPOCH);
    let fmt = time::macros::format_description!("[hour]:[minute]:[second].[subsecond digits:3]");
    t.format(&fmt).unwrap_or_default()
}

fn positions(f: &ViewFrame) -> String {
    let mut v = Vec::new();
    if let Some(x) = f.stage_um.axis_um {
        v.push(format!("axis {x:.1} µm"));
    }
    if let Some(x) = f.stage_um.piezo_um {
        v.push(format!("piezo {x:.2} µm"));
    }
    if v.is_empty() {
        "stages not read".into()
    } else {
        v.join(", ")
    }
}

/// Width of the sharpness bar, characters.
const BAR: usize = 20;

/// One line per target; `best` keeps each target's sharpest focus so far (the bar's full).
fn target_lines(targets: &[ViewTarget], best: &mut HashMap<String, f64>) -> Vec<String> {
    if targets.is_empty() {
        return vec!["  no target found".into()];
    }
    targets
        .iter()
        .enumerate()
        .map(|(i, t)| {
            let name = t.name.clone().unwrap_or_else(|| format!("#{}", i + 1));
            let bar = match t.focus {
                Some(f) => {
                    let b = best.entry(name.clone()).or_insert(f);
                    *b = b.max(f);
                    let filled = ((f / *b) * BAR as f64).round() as usize;
                    format!(
                        "[{}{}] focus {f:.3} (edge σ {:.2} px)",
                        "#".repeat(filled.min(BAR)),
                        " ".repeat(BAR - filled.min(BAR)),
                        t.edge_sigma_px.unwrap_or(f64::NAN)
                    )
                }
                None => format!("[{}] no contrast", " ".repeat(BAR)),
            };
            format!(
                "  {name:<6} centre ({:.2}, {:.2}) px = ({:.1}, {:.1}) µm  offset ({:.1}, {:.1}) µm  {bar}{}",
                t.centre_px[0],
                t.centre_px[1],
                t.centre_um[0],
                t.centre_um[1],
                t.offset_um[0],
                t.offset_um[1],
                t.error
                    .as_ref()
                    .map(|e| format!("  ({e})"))
                    .unwrap_or_default()
            )
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fps_outside_the_daemons_range_is_refused_before_sending() {
        assert_eq!(parse_fps("5"), Ok(5.0));
        assert_eq!(parse_fps("0.01"), Ok(0.01));
        for bad in ["1e-300", "0", "-0", "61", "NaN", "inf", "x"] {
            assert!(parse_fps(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn crops_parse_or_say_what_is_expected() {
        assert_eq!(parse_crop("1, 2,30,40"), Ok([1, 2, 30, 40]));
        assert!(parse_crop("1,2,3").unwrap_err().contains("four numbers"));
        assert!(parse_crop("a,b,c,d")
            .unwrap_err()
            .contains("X,Y,WIDTH,HEIGHT"));
    }

    #[test]
    fn the_bar_is_scaled_to_the_best_seen() {
        let t = |f: f64| ViewTarget {
            name: Some("A".into()),
            centre_px: [1.0, 2.0],
            centre_um: [774.0, 1548.0],
            offset_um: [0.0, 0.0],
            outer_radius_px: 10.0,
            inner_radius_px: 4.0,
            focus: Some(f),
            edge_sigma_px: Some(1.0),
            error: None,
        };
        let mut best = HashMap::new();
        let full = target_lines(&[t(0.2)], &mut best);
        assert!(
            full[0].contains(&format!("[{}]", "#".repeat(BAR))),
            "{}",
            full[0]
        );
        let half = target_lines(&[t(0.1)], &mut best);
        let want = format!("[{}{}]", "#".repeat(BAR / 2), " ".repeat(BAR / 2));
        assert!(half[0].contains(&want), "{}", half[0]);
    }
}
