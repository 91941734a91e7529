//! The `rigctl` command line: one module per subcommand, wired here.

pub mod hw;
pub mod process;

use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "rigctl",
    version,
    about = "Control a rigd metrology rig, or process frames offline"
)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Subcommand)]
pub enum Command {
    /// Measure target offsets in a folder of frames (frames/*.png + steps.csv), offline.
    Process(process::ProcessArgs),
    /// Talk to the configured hardware directly (bring-up; only when no daemon holds it).
    Hw(hw::HwArgs),
}

/// Entry point of the `rigctl` binary.
pub fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    match cli.command {
        Command::Process(a) => process::run(a),
        Command::Hw(a) => hw::run(a),
    }
}
