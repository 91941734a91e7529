//! One image channel as f32, row-major: what the estimators and reconstructions work on.

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
    /// Whether the whole ROI lies inside a `width` x `height` image.
    pub fn fits_in(&self, width: usize, height: usize) -> bool {
        self.x as usize + self.w as usize <= width && self.y as usize + self.h as usize <= height
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
        assert!(ch < 3, "channel {ch} out of 0..3");
        let lut = response.table();
        let data = img
            .as_raw()
            .chunks_exact(3)
            .map(|p| lut[p[ch] as usize])
            .collect();
        Plane {
            width: img.width() as usize,
            height: img.height() as usize,
            data,
        }
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
        assert!(ch < 3, "channel {ch} out of 0..3");
        let lut = response.table();
        let (iw, ih) = (img.width() as usize, img.height() as usize);
        let x0 = (roi.x as usize).min(iw);
        let y0 = (roi.y as usize).min(ih);
        let x1 = (roi.x as usize + roi.w as usize).min(iw);
        let y1 = (roi.y as usize + roi.h as usize).min(ih);
        let raw = img.as_raw();
        let mut data = Vec::with_capacity((x1 - x0) * (y1 - y0));
        for y in y0..y1 {
            let row = &raw[(y * iw + x0) * 3..(y * iw + x1) * 3];
            data.extend(row.chunks_exact(3).map(|p| lut[p[ch] as usize]));
        }
        Plane {
            width: x1 - x0,
            height: y1 - y0,
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
