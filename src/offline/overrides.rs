//! Processing settings given on a command line, each overriding a session's recorded one,
//! and the stable name of a set of them (`processed/<settings>/`).

use crate::acquisition::{JobRegistration, Processing};
use crate::pipeline::{Combine, Estimator};
use serde::{Deserialize, Serialize};

/// What the command line sets; `None` keeps the session's recorded value (a plain folder's
/// defaults: `rigctl process`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Overrides {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub k: Option<u32>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub estimator: Option<Estimator>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub combine: Option<Combine>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub registration: Option<JobRegistration>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub whole_frame: Option<bool>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scale_um_per_px: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub axis_dir: Option<[f64; 2]>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub piezo_dir: Option<[f64; 2]>,
    /// The camera's output curve, for sessions recorded before it was kept (or wrong).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub response: Option<crate::pipeline::Response>,
    /// The print's ink density statistics, for sessions recorded without them.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ink_prior: Option<crate::pipeline::InkPrior>,
    /// Whether runs take the applied calibration's learnt ink statistics (`false`: not).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub calibration_ink: Option<bool>,
}

impl Overrides {
    /// Nothing overridden: each run is processed with its recorded options.
    pub fn is_empty(&self) -> bool {
        *self == Overrides::default()
    }

    /// The overrides a replay takes (the rest are the rig's: [`Overrides::rig`]).
    pub fn processing(&self) -> Processing {
        Processing {
            k: self.k,
            estimator: self.estimator,
            combine: self.combine,
            registration: self.registration,
            whole_frame: self.whole_frame,
        }
    }

    /// `rig` with the scale and the stages' directions overridden.
    pub fn rig(&self, rig: &crate::rig::RigInfo) -> crate::rig::RigInfo {
        let mut r = rig.clone();
        if let Some(s) = self.scale_um_per_px {
            r.scale_um_per_px = s;
        }
        if let Some(d) = self.axis_dir {
            r.axis_dir = d;
        }
        if let Some(d) = self.piezo_dir {
            r.piezo_dir = Some(d);
        }
        if let Some(c) = self.response {
            r.response = c;
        }
        if let Some(p) = self.ink_prior {
            r.ink_prior = Some(p);
        }
        r
    }

    /// The settings' folder name under a session's `processed/`: the overridden settings in
    /// a fixed order, each as the command line spells it (`fit-interp-k10-image`,
    /// `k5`, `paper-commanded`); `recorded` when nothing is overridden. The same flags give
    /// the same name in any order; `settings.json` beside the result holds them in full.
    pub fn settings_name(&self) -> String {
        use crate::text::wire_name as wire;
        let mut parts: Vec<String> = Vec::new();
        if let Some(e) = &self.estimator {
            parts.push(wire(e));
        }
        if let Some(c) = &self.combine {
            parts.push(wire(c));
        }
        if let Some(k) = self.k {
            parts.push(format!("k{k}"));
        }
        if let Some(r) = &self.registration {
            parts.push(wire(r));
        }
        if let Some(w) = self.whole_frame {
            parts.push(if w { "whole" } else { "windows" }.into());
        }
        if let Some(s) = self.scale_um_per_px {
            parts.push(format!("scale{}", number(s)));
        }
        if let Some([x, y]) = self.axis_dir {
            parts.push(format!("axis{}_{}", number(x), number(y)));
        }
        if let Some([x, y]) = self.piezo_dir {
            parts.push(format!("piezo{}_{}", number(x), number(y)));
        }
        if let Some(c) = &self.response {
            parts.push(wire(c));
        }
        if let Some(p) = &self.ink_prior {
            parts.push(format!(
                "ink{}_{}",
                number(p.density_rms),
                number(p.corr_um)
            ));
        }
        if let Some(c) = self.calibration_ink {
            parts.push(if c { "calink" } else { "nocalink" }.into());
        }
        match parts.is_empty() {
            true => "recorded".into(),
            false => parts.join("-"),
        }
    }
}

/// A number in a folder name: its shortest form, `m` for a minus (`-1` -> `m1`).
fn number(v: f64) -> String {
    format!("{v}").replace('-', "m")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn settings_names_are_stable_and_spell_the_flags() {
        assert_eq!(Overrides::default().settings_name(), "recorded");
        let o = Overrides {
            k: Some(10),
            estimator: Some(Estimator::Fit),
            combine: Some(Combine::Interp),
            registration: Some(JobRegistration::Image),
            ..Overrides::default()
        };
        assert_eq!(o.settings_name(), "fit-interp-k10-image");
        let o = Overrides {
            registration: Some(JobRegistration::Interferometer),
            scale_um_per_px: Some(770.5),
            axis_dir: Some([-1.0, 0.0]),
            ..Overrides::default()
        };
        assert_eq!(o.settings_name(), "interferometer-scale770.5-axism1_0");
        let o = Overrides {
            ink_prior: Some(crate::pipeline::InkPrior {
                density_rms: 0.04,
                corr_um: 3000.0,
            }),
            ..Overrides::default()
        };
        assert_eq!(o.settings_name(), "ink0.04_3000");
        let o = Overrides {
            calibration_ink: Some(false),
            ..Overrides::default()
        };
        assert_eq!(o.settings_name(), "nocalink");
        assert!(!o.is_empty());
    }
}
