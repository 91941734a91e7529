//! Target boards: what is printed on the board the camera looks at, in micrometres.
//!
//! A board file (`config/boards/*.toml`) lists targets, each an outer ring around an inner
//! disk (or an inner ring), with the nominal offset of the inner centre from the outer one.
//! Board coordinates: x to the right, y down, origin at the board's top-left corner.
//! rigd reads the same files to name the targets it finds and to compare with the nominal
//! offsets; the simulator renders them.

use serde::{Deserialize, Serialize};
use std::path::Path;

/// One printed shape, centred on its own centre.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase", deny_unknown_fields)]
pub enum Shape {
    Disk {
        radius_um: f64,
    },
    Ring {
        inner_radius_um: f64,
        outer_radius_um: f64,
    },
}

impl Shape {
    /// Its edges' radii, `[inner, outer]` (a disk's one edge twice): the circles whose
    /// apparent centres a calibration's conversion averages.
    pub fn edges_um(&self) -> [f64; 2] {
        match *self {
            Shape::Ring {
                inner_radius_um,
                outer_radius_um,
            } => [inner_radius_um, outer_radius_um],
            Shape::Disk { radius_um } => [radius_um; 2],
        }
    }

    /// Radius of the outermost edge.
    pub fn outer_radius_um(&self) -> f64 {
        match *self {
            Shape::Disk { radius_um } => radius_um,
            Shape::Ring {
                outer_radius_um, ..
            } => outer_radius_um,
        }
    }
}

/// A target as resolved from the board file: every field filled in.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Target {
    pub name: String,
    /// Centre of the outer shape on the board.
    pub centre_um: [f64; 2],
    /// Nominal offset: inner centre minus outer centre.
    pub offset_um: [f64; 2],
    pub outer: Shape,
    pub inner: Shape,
}

impl Target {
    pub fn inner_centre_um(&self) -> [f64; 2] {
        [
            self.centre_um[0] + self.offset_um[0],
            self.centre_um[1] + self.offset_um[1],
        ]
    }
}

/// Red things on the board that are not targets (labels, marks): detection must reject them.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Clutter {
    pub centre_um: [f64; 2],
    pub shape: ClutterShape,
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase", deny_unknown_fields)]
pub enum ClutterShape {
    Disk { radius_um: f64 },
    Rect { width_um: f64, height_um: f64 },
}

/// A board with its targets resolved.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Board {
    pub name: String,
    /// Reflectance of the paper per channel (R, G, B), 0..1.
    pub paper_rgb: [f64; 3],
    /// Reflectance of the printed ink per channel.
    pub ink_rgb: [f64; 3],
    pub targets: Vec<Target>,
    pub clutter: Vec<Clutter>,
}

#[derive(Debug, thiserror::Error)]
pub enum BoardError {
    #[error("cannot read board file {path}: {source}")]
    Io {
        path: String,
        source: std::io::Error,
    },
    #[error("board file {path}: {message}")]
    Parse { path: String, message: String },
    #[error("board file {path}: target {target}: {message}")]
    Target {
        path: String,
        target: String,
        message: String,
    },
}

// The file format: defaults shared by all targets, overridable per target.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct BoardFile {
    name: String,
    #[serde(default = "default_paper")]
    paper_rgb: [f64; 3],
    #[serde(default = "default_ink")]
    ink_rgb: [f64; 3],
    #[serde(default)]
    defaults: TargetDefaults,
    #[serde(default)]
    targets: Vec<TargetFile>,
    #[serde(default)]
    clutter: Vec<Clutter>,
}

#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields)]
struct TargetDefaults {
    outer: Option<Shape>,
    inner: Option<Shape>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct TargetFile {
    name: String,
    centre_um: [f64; 2],
    offset_um: [f64; 2],
    outer: Option<Shape>,
    inner: Option<Shape>,
}

fn default_paper() -> [f64; 3] {
    [0.92, 0.91, 0.88]
}
fn default_ink() -> [f64; 3] {
    [0.78, 0.16, 0.17]
}

impl Board {
    /// Load and check a board file.
    pub fn load(path: impl AsRef<Path>) -> Result<Board, BoardError> {
        let path = path.as_ref();
        let text = std::fs::read_to_string(path).map_err(|source| BoardError::Io {
            path: path.display().to_string(),
            source,
        })?;
        Board::parse(&text, &path.display().to_string())
    }

    /// Parse board TOML; `origin` names the source in errors.
    pub fn parse(text: &str, origin: &str) -> Result<Board, BoardError> {
        let file: BoardFile = toml::from_str(text).map_err(|e| BoardError::Parse {
            path: origin.to_string(),
            message: e.to_string(),
        })?;
        let mut targets = Vec::with_capacity(file.targets.len());
        for t in file.targets {
            let err = |message: String| BoardError::Target {
                path: origin.to_string(),
                target: t.name.clone(),
                message,
            };
            let outer = t
                .outer
                .or(file.defaults.outer)
                .ok_or_else(|| err("no outer shape and no [defaults] outer".into()))?;
            let inner = t
                .inner
                .or(file.defaults.inner)
                .ok_or_else(|| err("no inner shape and no [defaults] inner".into()))?;
            let Shape::Ring {
                inner_radius_um: hole_um,
                outer_radius_um,
            } = outer
            else {
                return Err(err("the outer shape must be a ring".into()));
            };
            if !(hole_um > 0.0 && outer_radius_um > hole_um) {
                return Err(err(format!(
                    "outer ring radii must satisfy 0 < inner ({hole_um}) < outer ({outer_radius_um})"
                )));
            }
            let reach = inner.outer_radius_um() + t.offset_um[0].hypot(t.offset_um[1]);
            if reach >= hole_um {
                return Err(err(format!(
                    "inner shape reaches {reach} µm from the outer centre, into the outer ring (hole radius {hole_um} µm)"
                )));
            }
            targets.push(Target {
                name: t.name,
                centre_um: t.centre_um,
                offset_um: t.offset_um,
                outer,
                inner,
            });
        }
        Ok(Board {
            name: file.name,
            paper_rgb: file.paper_rgb,
            ink_rgb: file.ink_rgb,
            targets,
            clutter: file.clutter,
        })
    }

    /// The paper's board, shipped in `config/boards/paper.toml`.
    pub fn paper() -> Board {
        Board::parse(PAPER_BOARD, "config/boards/paper.toml")
            .expect("the shipped paper board parses")
    }

    pub fn target(&self, name: &str) -> Option<&Target> {
        self.targets.iter().find(|t| t.name == name)
    }
}

/// The shipped paper board, compiled in so `--sim` needs no files.
pub const PAPER_BOARD: &str = include_str!("../../config/boards/paper.toml");

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paper_board_has_the_papers_targets() {
        let b = Board::paper();
        assert_eq!(b.targets.len(), 12);
        let h: Vec<f64> = ["A", "B", "C", "D", "E", "F"]
            .iter()
            .map(|n| b.target(n).unwrap().offset_um[0])
            .collect();
        assert_eq!(h, vec![100.0, 1000.0, 2000.0, 3000.0, 4000.0, 5000.0]);
        assert_eq!(b.target("Fv").unwrap().offset_um, [0.0, 5000.0]);
    }

    #[test]
    fn inner_shape_into_the_ring_is_an_error_naming_the_target() {
        let text = r#"
name = "bad"
[defaults]
outer = { kind = "ring", inner_radius_um = 5000.0, outer_radius_um = 8000.0 }
inner = { kind = "disk", radius_um = 3000.0 }
[[targets]]
name = "X"
centre_um = [0.0, 0.0]
offset_um = [2500.0, 0.0]
"#;
        let e = Board::parse(text, "bad.toml").unwrap_err().to_string();
        assert!(e.contains("bad.toml") && e.contains("target X"), "{e}");
    }
}
