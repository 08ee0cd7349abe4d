//! The training loader: random (frame, camera) samples of a split, each with a downscaled
//! body view and a full-resolution face crop, background handling, a decoded-image cache with
//! a memory budget, and a worker thread that prepares samples ahead.
//!
//! Sample `i` is a pure function of `(seed, i)`, so a run resumed at step `i` sees the same
//! samples as an uninterrupted one. Background (Animatable Gaussians): a random colour per
//! sample (white when disabled) replaces the image outside the person (`image·α + bg·(1 − α)`);
//! the boundary band — the 5×5 dilation minus erosion of `α > 0.5`, plus soft pixels
//! `5/255 < α < 250/255` — is set to the background in the ground truth and reported so the
//! trainer does the same to its render.

use std::collections::{HashMap, VecDeque};
use std::sync::mpsc::{Receiver, SyncSender, sync_channel};
use std::sync::{Arc, Mutex};

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::DataError;
use crate::crop::{HeadBox, crop_view, head_box};
use crate::dataset::Dataset;
use crate::imgops::{morph, resize, resized_camera, scaled_size};
use crate::split::Split;
use f3g_camera::Camera;
use f3g_io::Image;
use f3g_rig::RigParams;

/// Loader settings.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct LoaderOptions {
    /// Scale of the body views relative to the captured images.
    pub body_scale: f32,
    /// Side of the face crops in pixels.
    pub face_size: usize,
    /// Head box enlargement.
    pub face_padding: f32,
    /// Budget of the decoded-image cache in bytes.
    pub cache_bytes: usize,
    /// Samples prepared ahead by the worker thread.
    pub prefetch: usize,
    /// Random background colour per sample (otherwise white).
    pub random_background: bool,
    /// Radius in capture pixels of the dilation/erosion that makes the boundary band (scaled
    /// to each view and rounded; Animatable Gaussians uses 2, captures with exact masks 0).
    pub band_radius: f32,
    pub seed: u64,
}

impl Default for LoaderOptions {
    fn default() -> Self {
        Self {
            body_scale: 0.5,
            face_size: 128,
            face_padding: 1.3,
            cache_bytes: 1 << 30,
            prefetch: 4,
            random_background: true,
            band_radius: 2.0,
            seed: 0,
        }
    }
}

/// One camera's view of a frame, ready for a loss.
#[derive(Clone, Debug)]
pub struct View {
    /// `[H, W, 3]` with the background composited and the boundary band set to it.
    pub image: Image,
    /// `[H, W, 1]` alpha.
    pub mask: Image,
    /// Boundary-band pixels.
    pub band: Vec<bool>,
    pub camera: Camera,
}

/// A training sample.
#[derive(Clone, Debug)]
pub struct Sample {
    pub index: u64,
    pub frame: usize,
    pub camera: usize,
    pub params: RigParams,
    pub background: [f32; 3],
    pub body: View,
    /// `None` when the head is not in view.
    pub face: Option<View>,
    pub head_box: Option<HeadBox>,
}

type Decoded = Arc<(Image, Image)>;

/// Decoded images and masks, evicted oldest-first beyond a byte budget.
pub struct ImageCache {
    budget: usize,
    used: usize,
    entries: HashMap<(usize, usize), Decoded>,
    order: VecDeque<(usize, usize)>,
}

impl ImageCache {
    pub fn new(budget: usize) -> Self {
        Self {
            budget,
            used: 0,
            entries: HashMap::new(),
            order: VecDeque::new(),
        }
    }

    fn get(&mut self, ds: &Dataset, camera: usize, frame: usize) -> Result<Decoded, DataError> {
        if let Some(d) = self.entries.get(&(camera, frame)) {
            return Ok(d.clone());
        }
        let d = Arc::new((ds.image(camera, frame)?, ds.mask(camera, frame)?));
        let bytes = 4 * (d.0.data.len() + d.1.data.len());
        while self.used + bytes > self.budget && !self.order.is_empty() {
            let old = self.order.pop_front().expect("non-empty");
            if let Some(e) = self.entries.remove(&old) {
                self.used -= 4 * (e.0.data.len() + e.1.data.len());
            }
        }
        if bytes <= self.budget {
            self.used += bytes;
            self.entries.insert((camera, frame), d.clone());
            self.order.push_back((camera, frame));
        }
        Ok(d)
    }
}

/// Composites over `background`, finds the boundary band and blanks it.
fn finish_view(
    image: Image,
    mask: Image,
    camera: Camera,
    background: [f32; 3],
    radius: usize,
) -> View {
    let (w, h) = (image.width, image.height);
    let alpha = &mask.data;
    let inside: Vec<bool> = alpha.iter().map(|&a| a > 0.5).collect();
    let (grown, shrunk) = (
        morph(&inside, w, h, radius, true),
        morph(&inside, w, h, radius, false),
    );
    let band: Vec<bool> = (0..w * h)
        .map(|p| (grown[p] && !shrunk[p]) || (alpha[p] > 5.0 / 255.0 && alpha[p] < 250.0 / 255.0))
        .collect();
    let mut out = image;
    for (p, rgb) in out.data.chunks_exact_mut(3).enumerate() {
        let a = if band[p] { 0.0 } else { alpha[p] };
        for (v, bg) in rgb.iter_mut().zip(background) {
            *v = *v * a + bg * (1.0 - a);
        }
    }
    View {
        image: out,
        mask,
        band,
        camera,
    }
}

/// A band radius in capture pixels as whole pixels of a view at `scale`.
fn view_radius(radius: f32, scale: f32) -> usize {
    (radius * scale).round().max(0.0) as usize
}

/// A view of `(camera, frame)` with a given background (evaluation and sampling share this).
pub fn make_view(
    ds: &Dataset,
    cache: &Mutex<ImageCache>,
    camera: usize,
    frame: usize,
    options: &LoaderOptions,
    background: [f32; 3],
) -> Result<(View, Option<View>, Option<HeadBox>), DataError> {
    let decoded = cache.lock().expect("cache lock").get(ds, camera, frame)?;
    let (full_image, full_mask) = (&decoded.0, &decoded.1);
    let cam = &ds.cameras[camera].camera;
    let (w, h) = scaled_size(full_image.width, full_image.height, options.body_scale);
    let body = finish_view(
        resize(full_image, w, h),
        resize(full_mask, w, h),
        resized_camera(cam, w, h),
        background,
        view_radius(options.band_radius, options.body_scale),
    );
    let rig = ds.rig()?;
    let posed = rig.pose(&ds.params[frame])?;
    let head: Vec<glam::Vec3> = rig
        .head_vertices()?
        .iter()
        .map(|&v| posed.vertices[v])
        .collect();
    let b = head_box(cam, &head, options.face_padding);
    let face = b.map(|b| {
        let (img, crop_cam) = crop_view(full_image, cam, &b, options.face_size, &background);
        let (mask, _) = crop_view(full_mask, cam, &b, options.face_size, &[0.0]);
        let scale = options.face_size as f32 / b.side;
        finish_view(
            img,
            mask,
            crop_cam,
            background,
            view_radius(options.band_radius, scale),
        )
    });
    Ok((body, face, b))
}

/// The (camera, frame) pairs of a split that have images.
pub fn available(ds: &Dataset, split: &Split) -> Vec<(usize, usize)> {
    split
        .frames
        .iter()
        .flat_map(|&f| split.cameras.iter().map(move |&c| (c, f)))
        .filter(|&(c, f)| ds.has_image(c, f))
        .collect()
}

/// Sample `index`: a pure function of the seed and the index.
pub fn make_sample(
    ds: &Dataset,
    pairs: &[(usize, usize)],
    cache: &Mutex<ImageCache>,
    options: &LoaderOptions,
    index: u64,
) -> Result<Sample, DataError> {
    let mut rng =
        ChaCha8Rng::seed_from_u64(options.seed ^ index.wrapping_mul(0x9e37_79b9_7f4a_7c15));
    let (camera, frame) = pairs[rng.random_range(0..pairs.len())];
    let background = if options.random_background {
        [rng.random(), rng.random(), rng.random()]
    } else {
        [1.0; 3]
    };
    let (body, face, head_box) = make_view(ds, cache, camera, frame, options, background)?;
    Ok(Sample {
        index,
        frame,
        camera,
        params: ds.params[frame].clone(),
        background,
        body,
        face,
        head_box,
    })
}

/// Samples prepared on a worker thread, in index order from `start`; with
/// [`Loader::with_preparation`], each one also goes through a function of the caller's on that
/// thread (the trainer uploads it to its device there, so a step never waits for host work).
pub struct Loader<T = Sample> {
    receiver: Receiver<Result<T, DataError>>,
    _worker: std::thread::JoinHandle<()>,
}

impl Loader<Sample> {
    pub fn new(
        ds: Arc<Dataset>,
        split: &Split,
        options: LoaderOptions,
        start: u64,
    ) -> Result<Self, DataError> {
        Self::with_preparation(ds, split, options, start, |s| s)
    }
}

impl<T: Send + 'static> Loader<T> {
    /// A loader whose worker also applies `prepare` to every sample.
    pub fn with_preparation(
        ds: Arc<Dataset>,
        split: &Split,
        options: LoaderOptions,
        start: u64,
        mut prepare: impl FnMut(Sample) -> T + Send + 'static,
    ) -> Result<Self, DataError> {
        let pairs = available(&ds, split);
        if pairs.is_empty() {
            return Err(DataError::Invalid("the split has no images".into()));
        }
        let (sender, receiver): (SyncSender<_>, _) = sync_channel(options.prefetch.max(1));
        let cache = Mutex::new(ImageCache::new(options.cache_bytes));
        let worker = std::thread::spawn(move || {
            for index in start.. {
                let sample = make_sample(&ds, &pairs, &cache, &options, index).map(&mut prepare);
                if sender.send(sample).is_err() {
                    return;
                }
            }
        });
        Ok(Self {
            receiver,
            _worker: worker,
        })
    }

    /// The next sample.
    pub fn next_sample(&mut self) -> Result<T, DataError> {
        self.receiver
            .recv()
            .map_err(|_| DataError::Invalid("the loader's worker stopped".into()))?
    }
}
