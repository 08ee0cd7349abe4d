//! The training loader: random (frame, camera) samples of a split, each with a body view at
//! `body_scale` and a face crop from the full-resolution image, background handling, a cache
//! of what each decoded image's views need (with a memory budget), and a worker thread that
//! prepares samples ahead.
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
use crate::crop::{HeadBox, crop_camera, head_box};
use crate::dataset::Dataset;
use crate::imgops::{crop_resize, morph, resize, resized_camera, scaled_size, window};
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

/// What the views of one captured image need, prepared once: the body image and mask at the
/// body scale, and the full-resolution pixels under the head box. At AvatarReX scale this is
/// ~4.5 MB per image instead of the 50 MB of the decoded 1536 × 2048 image and mask, so a
/// demo's whole capture stays decoded.
struct Prepared {
    body_image: Image,
    body_mask: Image,
    head: Option<HeadPatch>,
}

/// The full-resolution pixels around a head box: the box clipped to the image and grown by
/// [`HEAD_MARGIN`] pixels for the resampling, and where that window sits in the image.
struct HeadPatch {
    head_box: HeadBox,
    x0: usize,
    y0: usize,
    image: Image,
    mask: Image,
}

/// Source pixels kept around a head box: a bilinear tap at the box's edge reads one pixel
/// beyond it.
const HEAD_MARGIN: usize = 2;

impl HeadPatch {
    /// The window of `image` and `mask` under `head_box`; `None` when the box misses the
    /// image.
    fn new(image: &Image, mask: &Image, head_box: HeadBox) -> Option<Self> {
        let b = head_box;
        let lo = |v: f32| (v.floor() as i64 - HEAD_MARGIN as i64).max(0) as usize;
        let hi = |v: f32, n: usize| ((v.ceil() as i64 + HEAD_MARGIN as i64).max(0) as usize).min(n);
        let [x0, y0] = [lo(b.x0), lo(b.y0)];
        let [x1, y1] = [
            hi(b.x0 + b.side, image.width),
            hi(b.y0 + b.side, image.height),
        ];
        (x0 < x1 && y0 < y1).then(|| Self {
            head_box,
            x0,
            y0,
            image: window(image, x0, y0, x1, y1),
            mask: window(mask, x0, y0, x1, y1),
        })
    }

    /// The head box's image and mask resampled to `size × size`, as [`crop_resize`] would cut
    /// them from the whole image (`fill` outside it; the mask's fill is 0).
    fn crop(&self, size: usize, fill: &[f32]) -> (Image, Image) {
        let b = self.head_box;
        let (x0, y0) = (b.x0 - self.x0 as f32, b.y0 - self.y0 as f32);
        (
            crop_resize(&self.image, x0, y0, b.side, size, fill),
            crop_resize(&self.mask, x0, y0, b.side, size, &[0.0]),
        )
    }
}

impl Prepared {
    fn bytes(&self) -> usize {
        let head = self
            .head
            .as_ref()
            .map_or(0, |h| h.image.data.len() + h.mask.data.len());
        4 * (self.body_image.data.len() + self.body_mask.data.len() + head)
    }
}

/// Prepared views of captured images ([`Prepared`]), decoded once and evicted oldest-first
/// beyond a byte budget. The entries depend on the body scale and the head padding, so a
/// cache asked with other values than its entries were made with starts afresh.
pub struct ImageCache {
    budget: usize,
    used: usize,
    prepared_for: Option<(u32, u32)>,
    entries: HashMap<(usize, usize), Arc<Prepared>>,
    order: VecDeque<(usize, usize)>,
}

impl ImageCache {
    pub fn new(budget: usize) -> Self {
        Self {
            budget,
            used: 0,
            prepared_for: None,
            entries: HashMap::new(),
            order: VecDeque::new(),
        }
    }

    fn get(
        &mut self,
        ds: &Dataset,
        camera: usize,
        frame: usize,
        options: &LoaderOptions,
    ) -> Result<Arc<Prepared>, DataError> {
        let key = Some((options.body_scale.to_bits(), options.face_padding.to_bits()));
        if self.prepared_for != key {
            self.entries.clear();
            self.order.clear();
            self.used = 0;
            self.prepared_for = key;
        }
        if let Some(p) = self.entries.get(&(camera, frame)) {
            return Ok(p.clone());
        }
        let p = Arc::new(prepare(ds, camera, frame, options)?);
        let bytes = p.bytes();
        while self.used + bytes > self.budget && !self.order.is_empty() {
            let old = self.order.pop_front().expect("non-empty");
            if let Some(e) = self.entries.remove(&old) {
                self.used -= e.bytes();
            }
        }
        if bytes <= self.budget {
            self.used += bytes;
            self.entries.insert((camera, frame), p.clone());
            self.order.push_back((camera, frame));
        }
        Ok(p)
    }
}

/// Decodes `(camera, frame)` and keeps what its views need.
fn prepare(
    ds: &Dataset,
    camera: usize,
    frame: usize,
    options: &LoaderOptions,
) -> Result<Prepared, DataError> {
    let (image, mask) = (ds.image(camera, frame)?, ds.mask(camera, frame)?);
    let (w, h) = scaled_size(image.width, image.height, options.body_scale);
    let rig = ds.rig()?;
    let posed = rig.pose(&ds.params[frame])?;
    let head: Vec<glam::Vec3> = rig
        .head_vertices()?
        .iter()
        .map(|&v| posed.vertices[v])
        .collect();
    let head = head_box(&ds.cameras[camera].camera, &head, options.face_padding)
        .and_then(|b| HeadPatch::new(&image, &mask, b));
    Ok(Prepared {
        body_image: resize(&image, w, h),
        body_mask: resize(&mask, w, h),
        head,
    })
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

/// A view of `(camera, frame)` with a given background (evaluation and sampling share this):
/// the body at `body_scale`, and the head crop resampled from the full-resolution image.
pub fn make_view(
    ds: &Dataset,
    cache: &Mutex<ImageCache>,
    camera: usize,
    frame: usize,
    options: &LoaderOptions,
    background: [f32; 3],
) -> Result<(View, Option<View>, Option<HeadBox>), DataError> {
    let prepared = cache
        .lock()
        .expect("cache lock")
        .get(ds, camera, frame, options)?;
    let cam = &ds.cameras[camera].camera;
    let body = finish_view(
        prepared.body_image.clone(),
        prepared.body_mask.clone(),
        resized_camera(cam, prepared.body_image.width, prepared.body_image.height),
        background,
        view_radius(options.band_radius, options.body_scale),
    );
    let face = prepared.head.as_ref().map(|h| {
        let size = options.face_size;
        let (img, mask) = h.crop(size, &background);
        finish_view(
            img,
            mask,
            crop_camera(cam, &h.head_box, size),
            background,
            view_radius(options.band_radius, size as f32 / h.head_box.side),
        )
    });
    Ok((body, face, prepared.head.as_ref().map(|h| h.head_box)))
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
        let cache = Arc::new(Mutex::new(ImageCache::new(options.cache_bytes)));
        Self::with_preparation(ds, split, options, cache, start, |s| s)
    }
}

impl<T: Send + 'static> Loader<T> {
    /// A loader whose worker also applies `prepare` to every sample. `cache` may be shared
    /// with other loaders of the same capture (a trainer's), so that a new loader finds the
    /// images the previous ones decoded.
    pub fn with_preparation(
        ds: Arc<Dataset>,
        split: &Split,
        options: LoaderOptions,
        cache: Arc<Mutex<ImageCache>>,
        start: u64,
        mut prepare: impl FnMut(Sample) -> T + Send + 'static,
    ) -> Result<Self, DataError> {
        let pairs = available(&ds, split);
        if pairs.is_empty() {
            return Err(DataError::Invalid("the split has no images".into()));
        }
        let (sender, receiver): (SyncSender<_>, _) = sync_channel(options.prefetch.max(1));
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

#[cfg(test)]
mod tests {
    use super::*;

    /// A test pattern whose every pixel differs.
    fn pattern(width: usize, height: usize, channels: usize) -> Image {
        let data = (0..width * height * channels)
            .map(|i| ((i * 7919) % 1013) as f32 / 1013.0)
            .collect();
        Image::from_vec(width, height, channels, data).unwrap()
    }

    #[test]
    fn a_head_crop_from_the_kept_window_is_the_crop_of_the_whole_image() {
        let (image, mask) = (pattern(90, 120, 3), pattern(90, 120, 1));
        let fill = [0.2, 0.4, 0.6];
        // Inside, shrunk (side > size) and enlarged, and reaching past each edge.
        for (x0, y0, side) in [
            (20.3, 30.7, 41.0),
            (10.0, 12.5, 17.0),
            (-15.2, 40.0, 50.0),
            (60.4, -8.1, 45.0),
            (70.0, 95.0, 60.0),
            (-30.0, -30.0, 200.0),
        ] {
            let head_box = HeadBox { x0, y0, side };
            let patch = HeadPatch::new(&image, &mask, head_box).unwrap();
            assert!(patch.image.data.len() < image.data.len() || side > 100.0);
            for size in [24, 32] {
                let (img, m) = patch.crop(size, &fill);
                let whole = crop_resize(&image, x0, y0, side, size, &fill);
                let whole_mask = crop_resize(&mask, x0, y0, side, size, &[0.0]);
                for (a, b) in img.data.iter().zip(&whole.data) {
                    assert!((a - b).abs() < 1e-5, "{head_box:?} {size}: {a} vs {b}");
                }
                for (a, b) in m.data.iter().zip(&whole_mask.data) {
                    assert!((a - b).abs() < 1e-5, "{head_box:?} {size}: {a} vs {b}");
                }
            }
        }
        let away = HeadBox {
            x0: 200.0,
            y0: 10.0,
            side: 30.0,
        };
        assert!(HeadPatch::new(&image, &mask, away).is_none());
    }
}
