//! `rigctl position`, `rigctl move`, `rigctl jog`, `rigctl stop`: manual control of the
//! stages through the daemon when no job runs (`daemon::manual`).

use crate::acquisition::StageKind;
use crate::cli::client::{Client, SocketArg};
use crate::daemon::protocol::Request;
use crate::daemon::protocol::{LaserReading, MoveReply, PositionReply, StageReading, StopReply};
use anyhow::Context;
use std::io::{IsTerminal, Read, Write};

#[derive(clap::Args, Debug)]
pub struct PositionArgs {
    #[command(flatten)]
    pub socket: SocketArg,
    /// Print the reply as JSON.
    #[arg(long)]
    pub json: bool,
}

#[derive(clap::Args, Debug)]
#[command(group(clap::ArgGroup::new("target").required(true).args(["to_um", "by_um"])))]
pub struct MoveArgs {
    #[command(flatten)]
    pub socket: SocketArg,
    /// The stage to move.
    #[arg(long, value_enum, default_value_t = StageKind::Axis)]
    pub stage: StageKind,
    /// Absolute target, µm (negative numbers need no `=`).
    #[arg(long, value_name = "UM", allow_negative_numbers = true, value_parser = crate::cli::process::finite)]
    pub to_um: Option<f64>,
    /// Relative move, µm (negative: towards lower positions).
    #[arg(long, value_name = "UM", allow_negative_numbers = true, value_parser = crate::cli::process::finite)]
    pub by_um: Option<f64>,
}

#[derive(clap::Args, Debug)]
pub struct JogArgs {
    #[command(flatten)]
    pub socket: SocketArg,
    /// The stage to jog.
    #[arg(long, value_enum, default_value_t = StageKind::Axis)]
    pub stage: StageKind,
    /// The first step, µm (`[` and `]` divide and multiply it by 10).
    #[arg(long, value_name = "UM", default_value_t = 100.0, value_parser = crate::cli::process::finite)]
    pub step_um: f64,
}

#[derive(clap::Args, Debug)]
pub struct StopArgs {
    #[command(flatten)]
    pub socket: SocketArg,
}

fn reading(r: &Option<StageReading>) -> String {
    match r {
        None => "-".into(),
        Some(StageReading {
            position_um: Some(p),
            state,
            ..
        }) => format!(
            "{p:.3} µm ({})",
            state.map_or("?".into(), |s| format!("{s:?}").to_lowercase())
        ),
        Some(StageReading { error, .. }) => {
            format!("unreadable: {}", error.as_deref().unwrap_or("?"))
        }
    }
}

fn read_position(c: &mut Client) -> anyhow::Result<PositionReply> {
    Ok(serde_json::from_value(c.request(&Request::Position {})?)?)
}

fn position_line(p: &PositionReply) -> String {
    let mut s = format!("axis {}", reading(&p.axis));
    if p.piezo.is_some() {
        s.push_str(&format!("   piezo {}", reading(&p.piezo)));
    }
    match &p.interferometer {
        Some(LaserReading {
            position_um: Some(x),
            ..
        }) => s.push_str(&format!("   xl80 {x:.3} µm")),
        Some(LaserReading { error: Some(e), .. }) => {
            s.push_str(&format!("   xl80 unreadable: {e}"))
        }
        _ => {}
    }
    if let Some(id) = p.job_id {
        s.push_str(&format!("   (where paused job {id} left it)"));
    }
    s
}

pub fn position(a: PositionArgs) -> anyhow::Result<()> {
    let mut c = a.socket.connect()?;
    let p = read_position(&mut c)?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&p)?);
    } else {
        println!("{}", position_line(&p));
    }
    Ok(())
}

fn move_line(m: &MoveReply) -> String {
    format!(
        "{} at {:.3} µm ({}){}",
        m.stage,
        m.position_um,
        format!("{:?}", m.state).to_lowercase(),
        match m.stopped {
            true => format!(", stopped short of {} µm", m.target_um),
            false => String::new(),
        }
    )
}

pub fn move_stage(a: MoveArgs) -> anyhow::Result<()> {
    let mut c = a.socket.connect()?;
    let r = c.request(&Request::Move {
        stage: a.stage,
        to_um: a.to_um,
        by_um: a.by_um,
    })?;
    let m: MoveReply = serde_json::from_value(r)?;
    println!("{}", move_line(&m));
    Ok(())
}

pub fn stop(a: StopArgs) -> anyhow::Result<()> {
    let mut c = a.socket.connect()?;
    let r: StopReply = serde_json::from_value(c.request(&Request::Stop {})?)?;
    println!("{}", r.message);
    Ok(())
}

/// What a key does in `jog`.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Key {
    Plus,
    Minus,
    Finer,
    Coarser,
    Stop,
    Quit,
}

/// Keys from raw input: arrows (ESC [ A..D), + - [ ] s q; anything else is skipped.
fn keys(bytes: &[u8]) -> Vec<Key> {
    let mut out = Vec::new();
    let mut i = 0;
    while i < bytes.len() {
        let k = match bytes[i] {
            0x1b if bytes.get(i + 1) == Some(&b'[') && i + 2 < bytes.len() => {
                i += 2;
                match bytes[i] {
                    b'A' | b'C' => Some(Key::Plus),
                    b'B' | b'D' => Some(Key::Minus),
                    _ => None,
                }
            }
            b'+' | b'=' => Some(Key::Plus),
            b'-' | b'_' => Some(Key::Minus),
            b'[' => Some(Key::Finer),
            b']' => Some(Key::Coarser),
            b's' | b' ' => Some(Key::Stop),
            b'q' | 0x03 | 0x04 => Some(Key::Quit),
            _ => None,
        };
        out.extend(k);
        i += 1;
    }
    out
}

/// The terminal in raw mode while jogging, restored on drop.
struct Raw(Option<nix::sys::termios::Termios>);

impl Raw {
    fn enter() -> Raw {
        use nix::sys::termios::{cfmakeraw, tcgetattr, tcsetattr, SetArg};
        let stdin = std::io::stdin();
        if !stdin.is_terminal() {
            return Raw(None);
        }
        let Ok(saved) = tcgetattr(&stdin) else {
            return Raw(None);
        };
        let mut raw = saved.clone();
        cfmakeraw(&mut raw);
        let _ = tcsetattr(&stdin, SetArg::TCSANOW, &raw);
        Raw(Some(saved))
    }
}

impl Drop for Raw {
    fn drop(&mut self) {
        if let Some(t) = &self.0 {
            let _ = nix::sys::termios::tcsetattr(
                std::io::stdin(),
                nix::sys::termios::SetArg::TCSANOW,
                t,
            );
        }
    }
}

/// `rigctl jog`: keys from the terminal (raw), or from stdin when it is not one
/// (`echo '++]+q' | rigctl jog`: the form for scripts). Each move waits for its end; `s`
/// is read between moves (a long move is stopped from another shell: `rigctl stop`).
pub fn jog(a: JogArgs) -> anyhow::Result<()> {
    anyhow::ensure!(
        a.step_um.is_finite() && a.step_um > 0.0,
        "--step-um must be a positive number of µm, not {}",
        a.step_um
    );
    let mut c = a.socket.connect()?;
    let mut step = a.step_um;
    let interactive = std::io::stdin().is_terminal();
    let raw = Raw::enter();
    let nl = if raw.0.is_some() { "\r\n" } else { "\n" };
    let mut out = std::io::stdout();
    if interactive {
        write!(
            out,
            "jog {}: arrows or +/- move by the step, [ ] change it, s stops, q quits{nl}",
            a.stage
        )?;
    }
    let p = read_position(&mut c)?;
    write!(out, "{}   step {step} µm{nl}", position_line(&p))?;
    let mut buf = [0u8; 64];
    loop {
        out.flush()?;
        let n = std::io::stdin().read(&mut buf).context("reading keys")?;
        if n == 0 {
            return Ok(());
        }
        for key in keys(&buf[..n]) {
            let by_um = match key {
                Key::Quit => return Ok(()),
                Key::Finer | Key::Coarser => {
                    step = if key == Key::Finer {
                        step / 10.0
                    } else {
                        step * 10.0
                    };
                    write!(out, "step {step} µm{nl}")?;
                    continue;
                }
                Key::Stop => {
                    let r: StopReply = serde_json::from_value(c.request(&Request::Stop {})?)?;
                    write!(out, "{}{nl}", r.message)?;
                    continue;
                }
                Key::Plus => step,
                Key::Minus => -step,
            };
            let req = Request::Move {
                stage: a.stage,
                to_um: None,
                by_um: Some(by_um),
            };
            match c.request(&req) {
                Ok(r) => {
                    let m: MoveReply = serde_json::from_value(r)?;
                    write!(out, "{}   step {step} µm{nl}", move_line(&m))?;
                }
                // A refused step (a limit, a job started) is said and the jog goes on.
                Err(e) => write!(out, "{e}{nl}")?,
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn negative_moves_parse_without_an_equals_sign_and_one_target_is_required() {
        use crate::cli::{Cli, Command};
        use clap::Parser;
        let cli =
            Cli::try_parse_from(["rigctl", "move", "--stage", "piezo", "--by-um", "-50"]).unwrap();
        let Command::Move(m) = cli.command else {
            panic!("not a move")
        };
        assert_eq!(
            (m.stage, m.to_um, m.by_um),
            (StageKind::Piezo, None, Some(-50.0))
        );
        let cli = Cli::try_parse_from(["rigctl", "move", "--to-um", "-1.5"]).unwrap();
        let Command::Move(m) = cli.command else {
            panic!("not a move")
        };
        assert_eq!((m.stage, m.to_um), (StageKind::Axis, Some(-1.5)));
        for bad in [
            &["rigctl", "move"][..],
            &["rigctl", "move", "--to-um", "1", "--by-um", "2"],
        ] {
            assert!(Cli::try_parse_from(bad).is_err(), "{bad:?}");
        }
    }

    #[test]
    fn arrows_and_keys_are_read_from_raw_bytes() {
        assert_eq!(
            keys(b"\x1b[A\x1b[B+-[]sqx\x1b[C\x1b[D"),
            vec![
                Key::Plus,
                Key::Minus,
                Key::Plus,
                Key::Minus,
                Key::Finer,
                Key::Coarser,
                Key::Stop,
                Key::Quit,
                Key::Plus,
                Key::Minus
            ]
        );
    }
}
