//! `[axis]` / `[piezo]` config tables: which driver, and its options, as one value the
//! daemon and `rigctl hw` can open.
//!
//! ```toml
//! [axis]
//! driver = "grbl"          # or "gcs", or "sim"
//! port = "/dev/ttyUSB0"
//! [axis.limits]
//! min_um = 0
//! max_um = 290000
//! max_step_um = 5000
//! ```

use super::gcs::{GcsOptions, GcsStage};
use super::grbl::{GrblOptions, GrblStage};
use super::limits::TravelLimits;
use super::sim_stage::SimStage;
use super::{HwError, Stage};
use crate::sim::motion::Axis;
use serde::{Deserialize, Serialize};
use std::sync::Arc;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "driver", rename_all = "snake_case")]
pub enum StageConfig {
    Grbl(GrblOptions),
    Gcs(GcsOptions),
    /// In-process simulated axis (no serial port).
    Sim(SimStageOptions),
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SimStageOptions {
    pub limits: TravelLimits,
}

impl StageConfig {
    /// Build the stage. Serial drivers open lazily (on first use); `sim_axis` is the
    /// simulated rig's axis, required by `driver = "sim"`.
    pub fn build(
        &self,
        name: &str,
        sim_axis: Option<Arc<Axis>>,
    ) -> Result<Box<dyn Stage>, HwError> {
        Ok(match self {
            StageConfig::Grbl(o) => Box::new(GrblStage::new(name, o.clone())?),
            StageConfig::Gcs(o) => Box::new(GcsStage::new(name, o.clone())?),
            StageConfig::Sim(o) => {
                o.limits.validate().map_err(|message| HwError::Other {
                    device: name.to_string(),
                    message,
                })?;
                let axis = sim_axis.ok_or_else(|| HwError::Other {
                    device: name.to_string(),
                    message: "driver = \"sim\" needs the simulated rig's axis".into(),
                })?;
                Box::new(SimStage::new(name, axis, o.limits))
            }
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn driver_tables_parse_and_unknown_keys_are_named() {
        let c: StageConfig = toml::from_str(
            "driver = \"grbl\"\nport = \"/dev/ttyUSB0\"\non_alarm = \"unlock\"\n\
             [limits]\nmin_um = 0\nmax_um = 1000\nmax_step_um = 100\n",
        )
        .unwrap();
        assert!(matches!(c, StageConfig::Grbl(ref o) if o.port == "/dev/ttyUSB0"));
        let c: StageConfig = toml::from_str(
            "driver = \"gcs\"\nport = \"/dev/ttyUSB1\"\n\
             [limits]\nmin_um = 0\nmax_um = 100\nmax_step_um = 10\n",
        )
        .unwrap();
        assert!(matches!(c, StageConfig::Gcs(ref o) if o.axis == "1"));
        let e = toml::from_str::<StageConfig>(
            "driver = \"grbl\"\nport = \"x\"\nbuad = 9600\n\
             [limits]\nmin_um = 0\nmax_um = 1\nmax_step_um = 1\n",
        )
        .unwrap_err();
        assert!(e.to_string().contains("buad"), "{e}");
        let e = toml::from_str::<StageConfig>("driver = \"stepper\"\n").unwrap_err();
        assert!(e.to_string().contains("stepper"), "{e}");
    }

    #[test]
    fn sim_needs_an_axis() {
        let c = StageConfig::Sim(SimStageOptions {
            limits: TravelLimits::new(0.0, 10.0, 1.0).unwrap(),
        });
        assert!(c.build("axis", None).is_err());
        let axis = Arc::new(Axis::new(Default::default()));
        let mut s = c.build("axis", Some(axis)).unwrap();
        assert_eq!(s.name(), "axis");
        assert!(matches!(s.move_abs(11.0), Err(HwError::Limit { .. })));
    }
}
