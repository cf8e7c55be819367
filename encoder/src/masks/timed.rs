//! A *timing model + mask model* pair, for benchmarks that must cost what SAM ViT-H costs and
//! still feed the lifting stage realistic masks.
//!
//! A SAM with random weights (the only ViT-H the benchmark machines have) keeps about 0.2 masks
//! per image after its filters, so a run on it does almost no `a_kj` work downstream; a cheap
//! stand-in that gives SAM-like masks (color-sam: 60–100 overlapping masks per image on the
//! synthetic terrain) costs far less than ViT-H. [`TimedMasks`] runs both on every image: the
//! timing model (encoder + all decoder batches + its filters; its masks are dropped) for the
//! cost, then the mask model, whose masks go downstream. The mask stage's time is the sum of the
//! two; [`TimedMasks::seconds`] keeps them apart.

use image::RgbImage;
use slag_common::Result;

use super::{Mask, MaskGenerator};

/// Runs `timing` on each image for its cost only, then returns `masks`' masks.
pub struct TimedMasks {
    timing: Box<dyn MaskGenerator>,
    masks: Box<dyn MaskGenerator>,
    name: String,
    timing_s: f64,
    masks_s: f64,
    timing_masks: u64,
}

impl TimedMasks {
    /// The pair; `name` is what the report records as the mask source (it should name both
    /// models, e.g. `sam timing=sam-vit_h masks=color-sam`).
    pub fn new(
        timing: Box<dyn MaskGenerator>,
        masks: Box<dyn MaskGenerator>,
        name: impl Into<String>,
    ) -> Self {
        TimedMasks {
            timing,
            masks,
            name: name.into(),
            timing_s: 0.0,
            masks_s: 0.0,
            timing_masks: 0,
        }
    }

    /// Seconds spent so far in the timing model and in the mask model, and the masks the timing
    /// model produced (and dropped).
    pub fn seconds(&self) -> (f64, f64, u64) {
        (self.timing_s, self.masks_s, self.timing_masks)
    }
}

impl MaskGenerator for TimedMasks {
    fn name(&self) -> &str {
        &self.name
    }

    /// The mask model's masks of `image`, after a full run of the timing model on it.
    ///
    /// Errors: either model's.
    fn generate(&mut self, image: &RgbImage) -> Result<Vec<Mask>> {
        let t0 = std::time::Instant::now();
        let dropped = self.timing.generate(image)?;
        let t1 = std::time::Instant::now();
        let masks = self.masks.generate(image)?;
        self.timing_s += (t1 - t0).as_secs_f64();
        self.masks_s += t1.elapsed().as_secs_f64();
        self.timing_masks += dropped.len() as u64;
        tracing::debug!(
            timing_s = (t1 - t0).as_secs_f64(),
            masks_s = t1.elapsed().as_secs_f64(),
            timing_masks = dropped.len(),
            masks = masks.len(),
            "timing model + mask model"
        );
        Ok(masks)
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    struct Fixed {
        n: usize,
        calls: std::sync::Arc<std::sync::atomic::AtomicUsize>,
    }

    impl MaskGenerator for Fixed {
        fn name(&self) -> &str {
            "fixed"
        }
        fn generate(&mut self, image: &RgbImage) -> Result<Vec<Mask>> {
            self.calls.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
            let (w, h) = image.dimensions();
            Ok((0..self.n)
                .map(|i| {
                    let mut px = vec![0u8; (w * h) as usize];
                    px[i] = 1;
                    Mask::from_pixels(w, h, px).unwrap()
                })
                .collect())
        }
    }

    #[test]
    fn runs_both_models_and_returns_the_mask_models_masks() {
        let calls = |_| std::sync::Arc::new(std::sync::atomic::AtomicUsize::new(0));
        let (ct, cm) = (calls(0), calls(1));
        let timing = Fixed {
            n: 1,
            calls: ct.clone(),
        };
        let masks = Fixed {
            n: 3,
            calls: cm.clone(),
        };
        let mut t = TimedMasks::new(Box::new(timing), Box::new(masks), "t+m");
        let img = RgbImage::new(4, 2);
        let got = t.generate(&img).unwrap();
        t.generate(&img).unwrap();
        assert_eq!(got.len(), 3);
        assert_eq!(got[2].area, 1);
        assert!(got[2].contains(2, 0));
        assert_eq!(ct.load(std::sync::atomic::Ordering::SeqCst), 2);
        assert_eq!(cm.load(std::sync::atomic::Ordering::SeqCst), 2);
        assert_eq!(t.seconds().2, 2);
        assert_eq!(t.name(), "t+m");
    }
}
