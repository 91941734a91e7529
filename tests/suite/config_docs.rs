//! Every ```toml block in the docs is parsed by the real parser, so the documented config
//! cannot drift from the one rigd reads (docs/stages.md once showed a schema rigd refused).
//!
//! Convention: a block is a rig config (`rigd::config::Config`) unless the line before its
//! fence says otherwise with `<!-- toml: KIND -->`; KIND `sim-rig` is the simulator's
//! `SimRigConfig` (`sim --config`, docs/sim.md). Every section of a rig config is optional,
//! so a fragment is a config as long as it shows its table headers (`[axis]`, not bare
//! keys): each table is then parsed as the type rigd gives it, unknown keys refused.
//! `config/*.toml` files are whole rig configs.

use rigd::config::Config;
use std::path::{Path, PathBuf};

/// One fenced block: where it starts (file, 1-based line), its kind and its text.
struct Block {
    file: PathBuf,
    line: usize,
    kind: String,
    text: String,
}

/// The ```toml blocks of a markdown text.
fn toml_blocks(file: &Path, text: &str) -> Vec<Block> {
    let lines: Vec<&str> = text.lines().collect();
    let mut blocks = Vec::new();
    let mut i = 0;
    while i < lines.len() {
        if lines[i].trim() != "```toml" {
            i += 1;
            continue;
        }
        let kind = i
            .checked_sub(1)
            .and_then(|p| lines[p].trim().strip_prefix("<!-- toml:"))
            .and_then(|k| k.strip_suffix("-->"))
            .map_or("rigd", str::trim)
            .to_string();
        let end = (i + 1..lines.len())
            .find(|&j| lines[j].trim() == "```")
            .unwrap_or_else(|| panic!("{}:{}: unterminated ```toml", file.display(), i + 1));
        blocks.push(Block {
            file: file.to_path_buf(),
            line: i + 1,
            kind,
            text: lines[i + 1..end].join("\n"),
        });
        i = end + 1;
    }
    blocks
}

/// Parse a block as its kind; the parser's message on failure.
fn check(b: &Block) -> Result<(), String> {
    match b.kind.as_str() {
        "rigd" => Config::from_toml_str(&b.text, &b.file)
            .map(drop)
            .map_err(|e| e.to_string()),
        "sim-rig" => toml::from_str::<rigd_sim::SimRigConfig>(&b.text)
            .map(drop)
            .map_err(|e| e.to_string()),
        other => Err(format!("unknown kind {other:?} (rigd, sim-rig)")),
    }
}

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn files(dir: &Path, ext: &str) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == ext))
        .collect();
    v.sort();
    v
}

#[test]
fn every_toml_block_in_the_docs_parses_with_the_real_parser() {
    let mut md = files(&root().join("docs"), "md");
    md.push(root().join("README.md"));
    let blocks: Vec<Block> = md
        .iter()
        .flat_map(|f| toml_blocks(f, &std::fs::read_to_string(f).unwrap()))
        .collect();
    // docs/stages.md (the stage tables) and docs/sim.md (the sim's config) at least.
    assert!(blocks.len() >= 2, "only {} toml blocks found", blocks.len());
    let failed: Vec<String> = blocks
        .iter()
        .filter_map(|b| {
            check(b)
                .err()
                .map(|e| format!("{}:{} ({}): {e}", b.file.display(), b.line, b.kind))
        })
        .collect();
    assert!(failed.is_empty(), "{}", failed.join("\n\n"));
}

#[test]
fn every_config_file_parses_as_a_rig_config() {
    let tomls = files(&root().join("config"), "toml");
    assert!(!tomls.is_empty());
    for f in tomls {
        Config::load(&f).unwrap_or_else(|e| panic!("{e}"));
    }
}

#[test]
fn a_block_that_drifted_is_caught() {
    // A drifted block: an `[axis.limits]` table rigd does not have.
    let md = "Text.\n\n```toml\n[axis]\ndriver = \"grbl\"\nport = \"/dev/ttyUSB0\"\n\
              [axis.limits]\nmin_um = 0\n```\n\n<!-- toml: sim-rig -->\n```toml\nseed = 1\n```\n";
    let blocks = toml_blocks(Path::new("drift.md"), md);
    assert_eq!(blocks.len(), 2);
    assert_eq!((blocks[0].line, blocks[0].kind.as_str()), (3, "rigd"));
    let e = check(&blocks[0]).unwrap_err();
    assert!(e.contains("limits"), "{e}");
    assert_eq!(blocks[1].kind, "sim-rig");
    check(&blocks[1]).unwrap();
}
