//! (being written)

#[derive(clap::Args)]
pub struct ProcessArgs {}

pub fn run(_args: ProcessArgs) -> anyhow::Result<()> {
    anyhow::bail!("not yet implemented")
}
