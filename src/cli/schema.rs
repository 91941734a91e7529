//! `rigctl schema`: print the protocol's JSON Schema (what docs/protocol.schema.json holds).

#[derive(clap::Args, Debug)]
pub struct SchemaArgs {}

pub fn run(_: SchemaArgs) -> anyhow::Result<()> {
    print!("{}", crate::daemon::protocol::schema_text());
    Ok(())
}
