//! (being written)

#[derive(clap::Args)]
pub struct HwArgs {}

pub fn run(_args: HwArgs) -> anyhow::Result<()> {
    anyhow::bail!("not yet implemented")
}
