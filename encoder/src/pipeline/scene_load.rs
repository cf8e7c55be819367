//! The scene's Gaussians loaded once for an encode and the geometric segments beside it
//! ([`super::segment_task`]).
//!
//! The load starts with the run, on a thread of its own, so that it overlaps the set-up of the
//! fronts (their models). The segmentation receives the Gaussians as soon as they are loaded
//! (its k-NN graph starts then); the encode's pool takes the same [`Arc`] once it has checked
//! the scene folder ([`super::SceneInput`]). Both read the same geometry
//! ([`PlyLoadOptions::default`]: means, scales, rotations, opacities, no SH colours), so one
//! copy serves both: nothing is cloned, and the scene is freed when the last of the two lets go
//! of it (the encode's finish keeps only the centres when it is the last, as with a scene of its
//! own).

use std::path::PathBuf;
use std::sync::{Arc, mpsc};
use std::thread::JoinHandle;
use std::time::Instant;

use slag_common::scene::{self, Gaussians, PlyLoadOptions};
use slag_common::{Error, Result};

/// The scene's Gaussians and the seconds their load took (its own time, not the time anyone
/// waited for it).
pub(crate) struct LoadedGaussians {
    /// The Gaussians, shared with the segmentation.
    pub(crate) gaussians: Arc<Gaussians>,
    /// Seconds the `.ply` took to load.
    pub(crate) seconds: f64,
}

/// A `.ply` being loaded on a thread of its own, for the encode; dropping it waits for that
/// thread, so that none outlives the run.
pub(crate) struct SceneLoad {
    loaded: mpsc::Receiver<Result<LoadedGaussians>>,
    handle: Option<JoinHandle<()>>,
}

impl SceneLoad {
    /// Starts loading `ply` ([`scene::load_ply`], [`PlyLoadOptions::default`]) on a thread named
    /// `slag-scene` and returns at once, with the receiver on which the segmentation gets the
    /// Gaussians; it is closed without them when the load fails (the encode reports the error:
    /// [`SceneLoad::wait`]).
    ///
    /// Errors: [`Error::Internal`] when the thread cannot be started.
    pub(crate) fn start(ply: PathBuf) -> Result<(Self, mpsc::Receiver<Arc<Gaussians>>)> {
        let (to_segments, for_segments) = mpsc::channel();
        let (to_encode, loaded) = mpsc::channel();
        let handle = std::thread::Builder::new()
            .name("slag-scene".into())
            .spawn(move || {
                let t0 = Instant::now();
                let out = scene::load_ply(&ply, PlyLoadOptions::default()).map(|g| {
                    let seconds = t0.elapsed().as_secs_f64();
                    let gaussians = Arc::new(g);
                    // A segmentation that was stopped has hung up: it needs no scene then.
                    let _ = to_segments.send(Arc::clone(&gaussians));
                    LoadedGaussians { gaussians, seconds }
                });
                drop(to_segments);
                // An encode that failed before it needed the scene has hung up: the Gaussians
                // are dropped with the unsent result.
                let _ = to_encode.send(out);
            })
            .map_err(|e| Error::internal(format!("scene loading thread: {e}")))?;
        let load = SceneLoad {
            loaded,
            handle: Some(handle),
        };
        Ok((load, for_segments))
    }

    /// Waits for the load and returns the Gaussians.
    ///
    /// Errors: the load's ([`scene::load_ply`]: the `.ply` unreadable or malformed);
    /// [`Error::Internal`] when the loading thread panicked.
    pub(crate) fn wait(self) -> Result<LoadedGaussians> {
        self.loaded
            .recv()
            .map_err(|_| Error::internal("the scene's loading thread ended without a result"))?
    }
}

impl Drop for SceneLoad {
    fn drop(&mut self) {
        if let Some(h) = self.handle.take() {
            // Its result went to the channel (or nobody wanted it); a panic there has already
            // been reported as the channel's closing.
            let _ = h.join();
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)] // tests fail loudly on purpose
mod tests {
    use super::*;

    #[test]
    fn the_segments_and_the_encode_share_one_copy() {
        let dir = tempfile::tempdir().unwrap();
        let ply = dir.path().join("scene.ply");
        let g = crate::synthetic::terrain_gaussians(&crate::synthetic::SyntheticSceneParams {
            gaussians: 200,
            ..Default::default()
        });
        slag_common::scene::write_ply(&ply, &g).unwrap();
        let (load, for_segments) = SceneLoad::start(ply.clone()).unwrap();
        let segments = for_segments.recv().unwrap();
        let encode = load.wait().unwrap();
        assert!(Arc::ptr_eq(&segments, &encode.gaussians));
        assert_eq!(
            *encode.gaussians,
            scene::load_ply(&ply, PlyLoadOptions::default()).unwrap()
        );
        drop(segments);
        // The last holder owns the scene again, without a copy.
        assert!(Arc::try_unwrap(encode.gaussians).is_ok());
    }

    #[test]
    fn a_failed_load_goes_to_the_encode_and_closes_the_segments_channel() {
        let dir = tempfile::tempdir().unwrap();
        let (load, for_segments) = SceneLoad::start(dir.path().join("missing.ply")).unwrap();
        assert!(for_segments.recv().is_err());
        assert!(matches!(load.wait(), Err(Error::Io { .. })));
    }
}
