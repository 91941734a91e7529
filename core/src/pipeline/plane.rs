//! One plane of an image as f32, row-major (a channel, or the channels mixed by their
//! contrast: [`Mix`]): what the estimators and reconstructions work on.

use super::lateral::{self, LateralColour};
use super::response::Response;
use serde::{Deserialize, Serialize};

/// A rectangle of pixels: columns `x..x+w`, rows `y..y+h`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Roi {
    pub x: u32,
    pub y: u32,
    pub w: u32,
    pub h: u32,
}

impl Roi {
    /// The whole of a `width` x `height` image.
    pub fn whole(width: usize, height: usize) -> Roi {
        Roi {
            x: 0,
            y: 0,
            w: width as u32,
            h: height as u32,
        }
    }

    /// Whether the whole ROI lies inside a `width` x `height` image.
    pub fn fits_in(&self, width: usize, height: usize) -> bool {
        self.x as usize + self.w as usize <= width && self.y as usize + self.h as usize <= height
    }
}

/// What a plane is made of: each channel (0 = R, 1 = G, 2 = B) decoded to linear light, then
/// weighted. Every channel of a target carries its edges; a weighted sum keeps the fit's
/// model (`L·(1 − c·cov)` is linear in the channels) and, weighted by the channels' ink
/// contrast, is the matched combination for noise alike in each: red ink on white paper
/// darkens green and blue alike, and the two together scatter less than green alone
/// (docs/method.md, "Measurement plane"). With a lens's lateral colour measured (by a
/// calibration), each channel is registered onto green before the sum: unregistered, one
/// edge of the plane would be two, a fraction of a pixel apart at the frame's corners.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Mix {
    pub weights: [f32; 3],
    pub lateral: Option<LateralColour>,
}

impl Mix {
    /// Channel `ch` alone.
    ///
    /// # Panics
    /// If `ch > 2` (a programming error, not bad input).
    pub fn channel(ch: usize) -> Mix {
        assert!(ch < 3, "channel {ch} out of 0..3");
        let mut weights = [0.0; 3];
        weights[ch] = 1.0;
        Mix {
            weights,
            lateral: None,
        }
    }

    /// The same mix with its channels registered for `lateral`.
    pub fn registered(self, lateral: Option<LateralColour>) -> Mix {
        Mix { lateral, ..self }
    }

    /// The channels weighted by their ink contrast (paper minus ink, DN; a channel the ink
    /// does not darken takes no weight), summing to 1: the plane's levels stay in DN. Green
    /// alone when no channel shows contrast.
    pub fn of_contrast(contrast: [f64; 3]) -> Mix {
        let c = contrast.map(|v| v.max(0.0));
        let sum: f64 = c.iter().sum();
        if sum <= 0.0 || !sum.is_finite() {
            return Mix::channel(1);
        }
        Mix {
            weights: c.map(|v| (v / sum) as f32),
            lateral: None,
        }
    }

    /// The channel it is, when it is one.
    fn single(&self) -> Option<usize> {
        let w = self.weights;
        (0..3).find(|&c| w[c] == 1.0 && w.iter().filter(|&&v| v != 0.0).count() == 1)
    }

    /// One pixel's value through the decoding table `lut`.
    #[inline]
    fn value(&self, lut: &[f32; 256], p: &[u8]) -> f32 {
        let w = self.weights;
        w[0] * lut[p[0] as usize] + w[1] * lut[p[1] as usize] + w[2] * lut[p[2] as usize]
    }

    /// The pixels of one row (RGB) into `out`; `single` is [`Mix::single`] (one channel
    /// reads one byte a pixel).
    fn extend(&self, single: Option<usize>, lut: &[f32; 256], row: &[u8], out: &mut Vec<f32>) {
        match single {
            Some(ch) => out.extend(row.chunks_exact(3).map(|p| lut[p[ch] as usize])),
            None => out.extend(row.chunks_exact(3).map(|p| self.value(lut, p))),
        }
    }
}

#[derive(Debug, Clone)]
pub struct Plane {
    pub width: usize,
    pub height: usize,
    pub data: Vec<f32>,
}

impl Plane {
    /// A zero plane.
    pub fn new(width: usize, height: usize) -> Plane {
        Plane {
            width,
            height,
            data: vec![0.0; width * height],
        }
    }

    /// Channel `ch` (0 = R, 1 = G, 2 = B) of an RGB image, in DN.
    ///
    /// # Panics
    /// If `ch > 2` (a programming error, not bad input).
    pub fn from_channel(img: &image::RgbImage, ch: usize) -> Plane {
        Plane::from_channel_in(img, ch, Response::Linear)
    }

    /// Channel `ch` in linear light through the camera's output curve `response`.
    pub fn from_channel_in(img: &image::RgbImage, ch: usize, response: Response) -> Plane {
        Plane::from_mix_in(img, Mix::channel(ch), response)
    }

    /// The channels mixed by `mix`, each in linear light through `response`.
    pub fn from_mix_in(img: &image::RgbImage, mix: Mix, response: Response) -> Plane {
        let (w, h) = (img.width() as usize, img.height() as usize);
        Plane::from_mix_roi_in(img, mix, Roi::whole(w, h), response)
    }

    /// Channel `ch` of the pixels of `roi` only (cheaper than the whole frame then `crop`).
    /// The part of `roi` outside the image is dropped.
    pub fn from_channel_roi(img: &image::RgbImage, ch: usize, roi: Roi) -> Plane {
        Plane::from_channel_roi_in(img, ch, roi, Response::Linear)
    }

    /// [`Plane::from_channel_roi`] in linear light through `response`.
    pub fn from_channel_roi_in(
        img: &image::RgbImage,
        ch: usize,
        roi: Roi,
        response: Response,
    ) -> Plane {
        Plane::from_mix_roi_in(img, Mix::channel(ch), roi, response)
    }

    /// The channels mixed by `mix` of the pixels of `roi`, each in linear light through
    /// `response`; the part of `roi` outside the image is dropped.
    pub fn from_mix_roi_in(img: &image::RgbImage, mix: Mix, roi: Roi, response: Response) -> Plane {
        let lut = response.table();
        let (iw, ih) = (img.width() as usize, img.height() as usize);
        let x0 = (roi.x as usize).min(iw);
        let y0 = (roi.y as usize).min(ih);
        let x1 = (roi.x as usize + roi.w as usize).min(iw);
        let y1 = (roi.y as usize + roi.h as usize).min(ih);
        let raw = img.as_raw();
        if let Some(lat) = mix.lateral.filter(|l| (0..3).any(|c| l.moves(c, (iw, ih)))) {
            return Plane::registered((raw, iw, ih), mix, &lat, lut, [x0, y0, x1, y1]);
        }
        let mut data = Vec::with_capacity((x1 - x0) * (y1 - y0));
        let single = mix.single();
        for y in y0..y1 {
            mix.extend(
                single,
                lut,
                &raw[(y * iw + x0) * 3..(y * iw + x1) * 3],
                &mut data,
            );
        }
        Plane {
            width: x1 - x0,
            height: y1 - y0,
            data,
        }
    }

    /// [`Plane::from_mix_roi_in`] with the channels `lat` displaces registered onto green.
    fn registered(
        (raw, iw, ih): (&[u8], usize, usize),
        mix: Mix,
        lat: &LateralColour,
        lut: &[f32; 256],
        [x0, y0, x1, y1]: [usize; 4],
    ) -> Plane {
        let (w, h) = (x1 - x0, y1 - y0);
        let mut data = vec![0.0f32; w * h];
        for (c, &weight) in mix.weights.iter().enumerate().filter(|(_, &w)| w != 0.0) {
            if lat.moves(c, (iw, ih)) {
                lateral::add_registered(
                    (raw, iw, ih),
                    (c, weight),
                    lat,
                    lut,
                    [x0, y0, x1, y1],
                    &mut data,
                );
                continue;
            }
            for y in y0..y1 {
                let row = &raw[(y * iw + x0) * 3..(y * iw + x1) * 3];
                let line = &mut data[(y - y0) * w..(y - y0 + 1) * w];
                for (o, p) in line.iter_mut().zip(row.chunks_exact(3)) {
                    *o += weight * lut[p[c] as usize];
                }
            }
        }
        Plane {
            width: w,
            height: h,
            data,
        }
    }

    #[inline]
    pub fn at(&self, x: usize, y: usize) -> f32 {
        self.data[y * self.width + x]
    }

    /// The pixels of `roi`; the part of `roi` outside the plane is dropped, so the result
    /// starts at (`roi.x`, `roi.y`) and may be smaller than asked.
    pub fn crop(&self, roi: Roi) -> Plane {
        let x0 = (roi.x as usize).min(self.width);
        let y0 = (roi.y as usize).min(self.height);
        let x1 = (roi.x as usize + roi.w as usize).min(self.width);
        let y1 = (roi.y as usize + roi.h as usize).min(self.height);
        let mut data = Vec::with_capacity((x1 - x0) * (y1 - y0));
        for y in y0..y1 {
            data.extend_from_slice(&self.data[y * self.width + x0..y * self.width + x1]);
        }
        Plane {
            width: x1 - x0,
            height: y1 - y0,
            data,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_mix_weighs_each_channel_by_its_ink_contrast() {
        // Red ink on white paper: green and blue dark alike, red a little; a channel the ink
        // brightens takes nothing.
        let m = Mix::of_contrast([20.0, 110.0, 70.0]);
        assert_eq!(m.weights, [0.1, 0.55, 0.35]);
        assert_eq!(Mix::of_contrast([-5.0, 0.0, 10.0]).weights, [0.0, 0.0, 1.0]);
        assert_eq!(Mix::of_contrast([0.0; 3]), Mix::channel(1));
        // Its plane is that sum of the decoded channels, on the whole image and on a ROI.
        let img =
            image::RgbImage::from_fn(4, 3, |x, y| image::Rgb([10 * x as u8, 100, 7 * y as u8]));
        let p = Plane::from_mix_in(&img, m, Response::Linear);
        let want = |x: f32, y: f32| 0.1 * 10.0 * x + 0.55 * 100.0 + 0.35 * 7.0 * y;
        assert!((p.at(3, 2) - want(3.0, 2.0)).abs() < 1e-4, "{}", p.at(3, 2));
        let roi = Roi {
            x: 1,
            y: 1,
            w: 2,
            h: 2,
        };
        let q = Plane::from_mix_roi_in(&img, m, roi, Response::Linear);
        assert!((q.at(1, 1) - want(2.0, 2.0)).abs() < 1e-4);
        // Through the sRGB curve each channel is decoded before the sum.
        let lut = Response::Srgb.table();
        let s = Plane::from_mix_in(&img, m, Response::Srgb);
        let dec = 0.1 * lut[30] + 0.55 * lut[100] + 0.35 * lut[14];
        assert!((s.at(3, 2) - dec).abs() < 1e-3, "{} vs {dec}", s.at(3, 2));
    }

    #[test]
    fn channel_and_crop_pick_the_right_pixels() {
        let img = image::RgbImage::from_fn(5, 4, |x, y| image::Rgb([x as u8, y as u8, 7]));
        let g = Plane::from_channel(&img, 1);
        assert_eq!((g.width, g.height), (5, 4));
        assert_eq!(g.at(3, 2), 2.0);
        let r = Plane::from_channel(&img, 0).crop(Roi {
            x: 2,
            y: 1,
            w: 10,
            h: 2,
        });
        assert_eq!((r.width, r.height), (3, 2));
        assert_eq!(r.at(0, 0), 2.0);
        assert_eq!(r.at(2, 1), 4.0);
        let roi = Roi {
            x: 1,
            y: 1,
            w: 2,
            h: 2,
        };
        let direct = Plane::from_channel_roi(&img, 0, roi);
        assert_eq!(direct.data, Plane::from_channel(&img, 0).crop(roi).data);
    }
}
