//! The camera's output curve: how its DN encode light. The fit's model is linear in light
//! (the ink's contrast scales the paper's level), so frames from a camera that encodes with
//! the sRGB curve, as UVC webcams do, are taken back to linear light before they are
//! measured. Through the curve, the fitted edge of a darker patch of ink moves otherwise
//! than a lighter one's, and uneven ink becomes a bias (docs/method.md).

use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[cfg_attr(feature = "schemars", derive(schemars::JsonSchema))]
#[serde(rename_all = "snake_case")]
pub enum Response {
    /// DN proportional to light (a machine-vision camera with gamma 1, the ideal sim).
    #[default]
    Linear,
    /// The sRGB curve (IEC 61966-2-1): UVC webcams, the sim's `webcam` camera.
    Srgb,
}

impl Response {
    /// Linear DN (0..=255) of each 8-bit value.
    pub fn table(self) -> &'static [f32; 256] {
        static LINEAR: std::sync::OnceLock<[f32; 256]> = std::sync::OnceLock::new();
        static SRGB: std::sync::OnceLock<[f32; 256]> = std::sync::OnceLock::new();
        match self {
            Response::Linear => LINEAR.get_or_init(|| std::array::from_fn(|v| v as f32)),
            Response::Srgb => SRGB.get_or_init(|| {
                std::array::from_fn(|v| {
                    let e = v as f64 / 255.0;
                    let l = if e <= 0.040_45 {
                        e / 12.92
                    } else {
                        ((e + 0.055) / 1.055).powf(2.4)
                    };
                    (255.0 * l) as f32
                })
            }),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn srgb_decodes_to_linear_light_and_linear_is_the_identity() {
        let s = Response::Srgb.table();
        assert_eq!((s[0], s[255]), (0.0, 255.0));
        // sRGB 50 % grey (188) is ~50 % of the light; 128 is ~21.6 %.
        assert!((s[188] / 255.0 - 0.503).abs() < 0.002, "{}", s[188]);
        assert!((s[128] / 255.0 - 0.2158).abs() < 0.001, "{}", s[128]);
        assert!(s.windows(2).all(|w| w[1] > w[0]));
        let l = Response::Linear.table();
        assert!((0..256).all(|v| l[v] == v as f32));
    }
}
