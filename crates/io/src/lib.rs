//! File I/O shared by every stage.
//!
//! - Every write is atomic: data goes to a temporary file in the target directory, which is
//!   then renamed over the destination, so a crash never leaves a half-written output.
//! - Images in memory are `[H, W, C]` row-major `f32` in `[0, 1]`, RGB (not BGR).
//! - Errors name the file and say what was expected.

pub mod memory;
mod outputs;
pub mod text;

pub use outputs::{MANIFEST, OutputDir, remove_pending_temporaries};

use std::io::{Cursor, Read, Write};
use std::path::{Path, PathBuf};

/// A file could not be read, decoded or written.
#[derive(Debug, thiserror::Error)]
#[error("{path}: {reason}")]
pub struct IoError {
    /// The file concerned.
    pub path: PathBuf,
    /// What went wrong.
    pub reason: String,
}

impl IoError {
    /// An error about `path`.
    pub fn new(path: &Path, reason: impl ToString) -> Self {
        Self {
            path: path.to_path_buf(),
            reason: reason.to_string(),
        }
    }
}

/// How the temporary files of [`write_atomic`] begin (then the writer's process id and a dash):
/// a process killed mid-write leaves one behind (never a file under its final name), which the
/// next atomic write into that folder removes once the writer is gone.
pub const TEMPORARY_PREFIX: &str = ".f3g-tmp-";

/// Writes `bytes` to `path` atomically (temporary file in the same directory, then rename).
///
/// The file gets the mode a plain write would give it (`0o666` less the umask): the temporary
/// file's private `0o600` would otherwise survive the rename, and reports, images and `.ply`
/// files could not be shared or served on a multi-user machine. Checkpoints are written the
/// same way; the run folder's own permissions decide who reads a run.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), IoError> {
    let dir = path
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    if !dir.is_dir() {
        return Err(IoError::new(
            path,
            format!(
                "cannot be written: the folder {} does not exist",
                dir.display()
            ),
        ));
    }
    outputs::sweep_stale_temporaries(dir);
    let prefix = outputs::temporary_prefix();
    let mut builder = tempfile::Builder::new();
    builder.prefix(&prefix);
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        builder.permissions(std::fs::Permissions::from_mode(0o666));
    }
    let mut tmp = outputs::create_pending(&builder, dir).map_err(|e| {
        IoError::new(
            path,
            format!("cannot create a temporary file in {}: {e}", dir.display()),
        )
    })?;
    let temporary = tmp.path().to_path_buf();
    let written = (|| {
        tmp.write_all(bytes)?;
        tmp.as_file().sync_all()?;
        tmp.persist(path).map_err(|e| e.error)?;
        Ok::<(), std::io::Error>(())
    })();
    outputs::unregister_pending(&temporary);
    written.map_err(|e| IoError::new(path, e))
}

/// How much of an offending input an error message quotes.
pub const QUOTE_CHARS: usize = 200;

/// `text` in backticks for an error message, cut to its first [`QUOTE_CHARS`] characters (then
/// `…` and its whole length): a 5 MB token in a file is named, not echoed.
pub fn quoted(text: &str) -> String {
    match text.char_indices().nth(QUOTE_CHARS) {
        None => format!("`{text}`"),
        Some((end, _)) => format!("`{}…` ({} bytes)", &text[..end], text.len()),
    }
}

/// An image of `f32` samples, `[height, width, channels]` row-major.
#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    pub width: usize,
    pub height: usize,
    pub channels: usize,
    pub data: Vec<f32>,
}

impl Image {
    /// A `width × height` image with `channels` channels, every sample `value`.
    pub fn filled(width: usize, height: usize, channels: usize, value: f32) -> Self {
        Self {
            width,
            height,
            channels,
            data: vec![value; width * height * channels],
        }
    }

    /// Wraps `data`, checking its length.
    pub fn from_vec(
        width: usize,
        height: usize,
        channels: usize,
        data: Vec<f32>,
    ) -> Result<Self, String> {
        if data.len() != width * height * channels {
            return Err(format!(
                "{} samples for a {width}x{height}x{channels} image",
                data.len()
            ));
        }
        Ok(Self {
            width,
            height,
            channels,
            data,
        })
    }

    /// The samples of pixel `(x, y)`.
    pub fn pixel(&self, x: usize, y: usize) -> &[f32] {
        let at = (y * self.width + x) * self.channels;
        &self.data[at..at + self.channels]
    }

    /// Mutable samples of pixel `(x, y)`.
    pub fn pixel_mut(&mut self, x: usize, y: usize) -> &mut [f32] {
        let at = (y * self.width + x) * self.channels;
        &mut self.data[at..at + self.channels]
    }
}

fn decode(path: &Path) -> Result<image::DynamicImage, IoError> {
    image::ImageReader::open(path)
        .map_err(|e| IoError::new(path, e))?
        .with_guessed_format()
        .map_err(|e| IoError::new(path, e))?
        .decode()
        .map_err(|e| IoError::new(path, format!("cannot decode image: {e}")))
}

/// Reads a PNG or JPEG as RGB in `[0, 1]` (alpha dropped, grey expanded).
pub fn read_rgb(path: &Path) -> Result<Image, IoError> {
    let img = decode(path)?.into_rgb32f();
    let (w, h) = img.dimensions();
    Ok(Image {
        width: w as usize,
        height: h as usize,
        channels: 3,
        data: img.into_raw(),
    })
}

/// Reads a mask (grey, or the luminance of a colour image) as one channel in `[0, 1]`.
pub fn read_gray(path: &Path) -> Result<Image, IoError> {
    let img = decode(path)?.to_luma32f();
    let (w, h) = img.dimensions();
    Ok(Image {
        width: w as usize,
        height: h as usize,
        channels: 1,
        data: img.into_raw(),
    })
}

/// Reads only the size `(width, height)` of an image file, without decoding it.
pub fn image_size(path: &Path) -> Result<(usize, usize), IoError> {
    let (w, h) = image::ImageReader::open(path)
        .map_err(|e| IoError::new(path, e))?
        .with_guessed_format()
        .map_err(|e| IoError::new(path, e))?
        .into_dimensions()
        .map_err(|e| IoError::new(path, format!("cannot read the image header: {e}")))?;
    Ok((w as usize, h as usize))
}

/// A sample in `[0, 1]` as 8 bits, rounded half away from zero (NaN → 0). Written without
/// `f32::round`, which on the baseline x86-64 target is a call into libm's `roundf` per value:
/// 14 % of `f3g synth`'s samples went there (2026-11-28). `scaled − whole` is exact below 2²³,
/// so this is `round` to the bit.
fn to_u8(v: f32) -> u8 {
    let scaled = v.clamp(0.0, 1.0) * 255.0;
    let whole = scaled as u8;
    whole + u8::from(scaled - f32::from(whole) >= 0.5)
}

/// Encodes an image with 1, 3 or 4 channels as PNG (samples clamped to `[0, 1]`).
pub fn encode_png(img: &Image) -> Result<Vec<u8>, String> {
    let color = match img.channels {
        1 => image::ExtendedColorType::L8,
        3 => image::ExtendedColorType::Rgb8,
        4 => image::ExtendedColorType::Rgba8,
        c => return Err(format!("cannot write a {c}-channel image as PNG")),
    };
    let bytes: Vec<u8> = img.data.iter().map(|&v| to_u8(v)).collect();
    let mut out = Cursor::new(Vec::new());
    image::ImageEncoder::write_image(
        image::codecs::png::PngEncoder::new(&mut out),
        &bytes,
        img.width as u32,
        img.height as u32,
        color,
    )
    .map_err(|e| e.to_string())?;
    Ok(out.into_inner())
}

/// Writes an image as PNG, atomically.
pub fn write_png(path: &Path, img: &Image) -> Result<(), IoError> {
    let bytes = encode_png(img).map_err(|e| IoError::new(path, e))?;
    write_atomic(path, &bytes)
}

/// Writes a JPEG (quality 1–100, 4:4:4 from 90 up), atomically. Used for capture images, as
/// real datasets do.
pub fn write_jpeg(path: &Path, img: &Image, quality: u8) -> Result<(), IoError> {
    let color = match img.channels {
        1 => jpeg_encoder::ColorType::Luma,
        3 => jpeg_encoder::ColorType::Rgb,
        c => {
            return Err(IoError::new(
                path,
                format!("cannot write a {c}-channel image as JPEG"),
            ));
        }
    };
    let side = |n: usize, what: &str| {
        u16::try_from(n).map_err(|_| {
            IoError::new(
                path,
                format!("a JPEG's {what} is at most 65 535 pixels, not {n}"),
            )
        })
    };
    let (width, height) = (side(img.width, "width")?, side(img.height, "height")?);
    let bytes: Vec<u8> = img.data.iter().map(|&v| to_u8(v)).collect();
    let mut out = Vec::new();
    jpeg_encoder::Encoder::new(&mut out, quality)
        .encode(&bytes, width, height, color)
        .map_err(|e| IoError::new(path, e))?;
    write_atomic(path, &out)
}

/// Removes the entries of `dir` whose names `owned` accepts (`is_dir` tells folders, removed
/// whole): for a command that replaces a whole set of its files on the user's explicit
/// `--overwrite` (`f3g synth`). Commands that write into a folder on every run use
/// [`OutputDir`], which removes only files it recorded. Returns how many entries were removed; a
/// missing `dir` has none.
pub fn clear_outputs(dir: &Path, owned: impl Fn(&str, bool) -> bool) -> Result<usize, IoError> {
    let entries = match std::fs::read_dir(dir) {
        Ok(entries) => entries,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(0),
        Err(e) => return Err(IoError::new(dir, e)),
    };
    let mut removed = 0;
    for entry in entries {
        let entry = entry.map_err(|e| IoError::new(dir, e))?;
        let path = entry.path();
        let is_dir = entry
            .file_type()
            .map_err(|e| IoError::new(&path, e))?
            .is_dir();
        if owned(&entry.file_name().to_string_lossy(), is_dir) {
            if is_dir {
                std::fs::remove_dir_all(&path)
            } else {
                std::fs::remove_file(&path)
            }
            .map_err(|e| IoError::new(&path, e))?;
            removed += 1;
        }
    }
    Ok(removed)
}

/// Encodes `f32` data of the given shape as `.npy` (little-endian, C order).
pub fn encode_npy_f32(shape: &[usize], data: &[f32]) -> Result<Vec<u8>, String> {
    encode_npy(shape, data)
}

/// Writes `f32` data of the given shape as `.npy`, atomically.
pub fn write_npy_f32(path: &Path, shape: &[usize], data: &[f32]) -> Result<(), IoError> {
    let bytes = encode_npy_f32(shape, data).map_err(|e| IoError::new(path, e))?;
    write_atomic(path, &bytes)
}

/// Reads an `.npy` file as `f32` (any float or integer dtype is converted) with its shape.
pub fn read_npy_f32(path: &Path) -> Result<(Vec<usize>, Vec<f32>), IoError> {
    let bytes = std::fs::read(path).map_err(|e| IoError::new(path, e))?;
    let npy = npyz::NpyFile::new(&bytes[..])
        .map_err(|e| IoError::new(path, format!("not a valid .npy file: {e}")))?;
    npy_values(npy).map_err(|e| IoError::new(path, e))
}

/// A type `.npy` values are read as: every numeric dtype converts to `f32`; `i64` takes the
/// integer and boolean dtypes and refuses floats.
pub trait NpyScalar: Sized {
    /// What the type is called in errors.
    const NAME: &'static str;
    fn from_f64(v: f64) -> Option<Self>;
    fn from_i64(v: i64) -> Self;
    fn from_u64(v: u64) -> Self;
}

impl NpyScalar for f32 {
    const NAME: &'static str = "a numeric type";
    fn from_f64(v: f64) -> Option<Self> {
        Some(v as f32)
    }
    fn from_i64(v: i64) -> Self {
        v as f32
    }
    fn from_u64(v: u64) -> Self {
        v as f32
    }
}

impl NpyScalar for i64 {
    const NAME: &'static str = "an integer type";
    fn from_f64(_: f64) -> Option<Self> {
        None
    }
    fn from_i64(v: i64) -> Self {
        v
    }
    fn from_u64(v: u64) -> Self {
        v as i64
    }
}

/// Reads any plain numeric `.npy` stream as `T` values with its shape (C order required).
pub fn npy_values<T: NpyScalar, R: std::io::Read>(
    npy: npyz::NpyFile<R>,
) -> Result<(Vec<usize>, Vec<T>), String> {
    use npyz::{DType, TypeChar};
    if npy.order() != npyz::Order::C {
        return Err("Fortran-ordered arrays are not supported; save with C order".into());
    }
    let shape = checked_shape(npy.shape())?;
    let DType::Plain(ts) = npy.dtype() else {
        return Err(format!(
            "dtype {:?} is not a plain numeric type",
            npy.dtype()
        ));
    };
    let (kind, size) = (ts.type_char(), ts.size_field());
    let not_t = || format!("dtype {kind:?} of {size} bytes is not {}", T::NAME);
    let read_err = |e: std::io::Error| e.to_string();
    fn all<A, T>(values: Vec<A>, f: impl Fn(A) -> T) -> Vec<T> {
        values.into_iter().map(f).collect()
    }
    let floats = |values: Vec<f64>| -> Result<Vec<T>, String> {
        values
            .into_iter()
            .map(|v| T::from_f64(v).ok_or_else(not_t))
            .collect()
    };
    let values: Vec<T> = match (kind, size) {
        (TypeChar::Float, 4) => floats(all(npy.into_vec::<f32>().map_err(read_err)?, f64::from))?,
        (TypeChar::Float, 8) => floats(npy.into_vec::<f64>().map_err(read_err)?)?,
        (TypeChar::Int, 1) => all(npy.into_vec::<i8>().map_err(read_err)?, |v| {
            T::from_i64(v.into())
        }),
        (TypeChar::Int, 2) => all(npy.into_vec::<i16>().map_err(read_err)?, |v| {
            T::from_i64(v.into())
        }),
        (TypeChar::Int, 4) => all(npy.into_vec::<i32>().map_err(read_err)?, |v| {
            T::from_i64(v.into())
        }),
        (TypeChar::Int, 8) => all(npy.into_vec::<i64>().map_err(read_err)?, T::from_i64),
        (TypeChar::Uint, 1) => all(npy.into_vec::<u8>().map_err(read_err)?, |v| {
            T::from_u64(v.into())
        }),
        (TypeChar::Uint, 2) => all(npy.into_vec::<u16>().map_err(read_err)?, |v| {
            T::from_u64(v.into())
        }),
        (TypeChar::Uint, 4) => all(npy.into_vec::<u32>().map_err(read_err)?, |v| {
            T::from_u64(v.into())
        }),
        (TypeChar::Uint, 8) => all(npy.into_vec::<u64>().map_err(read_err)?, T::from_u64),
        (TypeChar::Bool, 1) => all(npy.into_vec::<bool>().map_err(read_err)?, |v| {
            T::from_u64(v.into())
        }),
        _ => return Err(not_t()),
    };
    Ok((shape, values))
}

/// The shape of an array whose element count fits in memory's address space: npyz multiplies
/// the header's dimensions unchecked, so a product that overflows would wrap to a small count
/// and the values would not match the shape the caller trusts.
fn checked_shape(shape: &[u64]) -> Result<Vec<usize>, String> {
    let count = shape
        .iter()
        .try_fold(1usize, |n, &d| n.checked_mul(usize::try_from(d).ok()?));
    match count {
        Some(n) if n <= isize::MAX as usize / 8 => Ok(shape.iter().map(|&d| d as usize).collect()),
        _ => Err(format!(
            "shape {shape:?} holds more values than memory can address"
        )),
    }
}

/// An `.npz` archive (as numpy's `savez`/`savez_compressed` write), with typed accessors whose
/// errors name the file and the array.
pub struct Npz<R: std::io::Read + std::io::Seek> {
    archive: zip::ZipArchive<R>,
    path: PathBuf,
}

impl Npz<std::io::BufReader<std::fs::File>> {
    /// Opens an `.npz` file.
    pub fn open(path: &Path) -> Result<Self, IoError> {
        let file = std::fs::File::open(path).map_err(|e| IoError::new(path, e))?;
        let archive = zip::ZipArchive::new(std::io::BufReader::new(file))
            .map_err(|e| IoError::new(path, format!("not a readable .npz archive: {e}")))?;
        Ok(Self {
            archive,
            path: path.to_path_buf(),
        })
    }
}

impl<'a> Npz<Cursor<&'a [u8]>> {
    /// Reads an `.npz` held in memory; `label` names it in errors.
    pub fn from_bytes(bytes: &'a [u8], label: &str) -> Result<Self, IoError> {
        let path = PathBuf::from(label);
        let archive = zip::ZipArchive::new(Cursor::new(bytes))
            .map_err(|e| IoError::new(&path, format!("not a readable .npz archive: {e}")))?;
        Ok(Self { archive, path })
    }
}

impl<R: std::io::Read + std::io::Seek> Npz<R> {
    /// The archive's array names.
    pub fn names(&self) -> Vec<String> {
        self.array_names().map(String::from).collect()
    }

    /// Whether the archive holds `name`.
    pub fn contains(&self, name: &str) -> bool {
        self.array_names().any(|n| n == name)
    }

    /// The members that are arrays (`NAME.npy`), by name.
    fn array_names(&self) -> impl Iterator<Item = &str> {
        self.archive
            .file_names()
            .filter_map(npyz::npz::array_name_from_file_name)
    }

    fn array(&mut self, name: &str) -> Result<npyz::NpyFile<zip::read::ZipFile<'_>>, IoError> {
        let path = self.path.clone();
        let member = match self
            .archive
            .by_name(&npyz::npz::file_name_from_array_name(name))
        {
            Ok(member) => member,
            Err(zip::result::ZipError::FileNotFound) => {
                return Err(IoError::new(&path, format!("missing array `{name}`")));
            }
            Err(e) => return Err(IoError::new(&path, format!("`{name}`: {e}"))),
        };
        npyz::NpyFile::new(member).map_err(|e| IoError::new(&path, format!("`{name}`: {e}")))
    }

    /// Array `name` as `f32` with its shape.
    pub fn f32(&mut self, name: &str) -> Result<(Vec<usize>, Vec<f32>), IoError> {
        let path = self.path.clone();
        npy_values(self.array(name)?).map_err(|e| IoError::new(&path, format!("`{name}`: {e}")))
    }

    /// Integer array `name` as `i64` with its shape.
    pub fn i64(&mut self, name: &str) -> Result<(Vec<usize>, Vec<i64>), IoError> {
        let path = self.path.clone();
        npy_values(self.array(name)?).map_err(|e| IoError::new(&path, format!("`{name}`: {e}")))
    }

    /// Array `name` as `f32`, which must have exactly `shape` and only finite values.
    pub fn f32_exact(&mut self, name: &str, shape: &[usize]) -> Result<Vec<f32>, IoError> {
        // The header first: a shape that lies is refused before anything is allocated.
        let got = self.shape(name)?;
        self.check_shape(name, &got, shape)?;
        let (_, values) = self.f32(name)?;
        match values.iter().position(|v| !v.is_finite()) {
            Some(i) => Err(IoError::new(
                &self.path,
                format!("`{name}`: non-finite value at flat index {i}"),
            )),
            None => Ok(values),
        }
    }

    /// Integer array `name` of exactly `shape` whose values are indices below `bound`.
    pub fn indices(
        &mut self,
        name: &str,
        shape: &[usize],
        bound: usize,
    ) -> Result<Vec<usize>, IoError> {
        let got = self.shape(name)?;
        self.check_shape(name, &got, shape)?;
        let (_, values) = self.i64(name)?;
        values
            .iter()
            .map(|&v| {
                usize::try_from(v)
                    .ok()
                    .filter(|&v| v < bound)
                    .ok_or_else(|| {
                        IoError::new(
                            &self.path,
                            format!("`{name}`: {v} is not an index below {bound}"),
                        )
                    })
            })
            .collect()
    }

    /// The shape of array `name` (read from its header only).
    pub fn shape(&mut self, name: &str) -> Result<Vec<usize>, IoError> {
        let path = self.path.clone();
        checked_shape(self.array(name)?.shape()).map_err(|e| IoError::new(&path, e))
    }

    fn check_shape(&self, name: &str, got: &[usize], shape: &[usize]) -> Result<(), IoError> {
        if got == shape {
            Ok(())
        } else {
            Err(IoError::new(
                &self.path,
                format!("`{name}` has shape {got:?}, expected {shape:?}"),
            ))
        }
    }

    /// The file this archive came from (or its label).
    pub fn path(&self) -> &Path {
        &self.path
    }
}

/// The values of one array to write into an `.npz`.
#[derive(Clone, Copy, Debug)]
pub enum NpyValues<'a> {
    F32(&'a [f32]),
    I64(&'a [i64]),
}

fn encode_npy<T: npyz::AutoSerialize + Copy>(
    shape: &[usize],
    data: &[T],
) -> Result<Vec<u8>, String> {
    use npyz::WriterBuilder;
    let expected: usize = shape.iter().product();
    if expected != data.len() {
        return Err(format!("{} values for shape {shape:?}", data.len()));
    }
    let mut buf = Vec::new();
    let shape: Vec<u64> = shape.iter().map(|&s| s as u64).collect();
    let mut writer = npyz::WriteOptions::new()
        .default_dtype()
        .shape(&shape)
        .writer(&mut buf)
        .begin_nd()
        .map_err(|e| e.to_string())?;
    writer
        .extend(data.iter().copied())
        .map_err(|e| e.to_string())?;
    writer.finish().map_err(|e| e.to_string())?;
    Ok(buf)
}

/// Reads `reader` to its end but no further than `expected + 1` bytes, the buffer grown as data
/// come rather than reserved: a decompressor over damaged data stops one byte past what its
/// header promised, and no size read from a file is allocated before the data bear it out. The
/// caller compares the length with `expected`.
pub fn read_at_most(reader: impl Read, expected: usize) -> std::io::Result<Vec<u8>> {
    let mut bytes = Vec::new();
    reader.take(expected as u64 + 1).read_to_end(&mut bytes)?;
    Ok(bytes)
}

/// How the arrays of an `.npz` are stored in its zip archive.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum NpzEntries {
    /// As they are (`numpy.savez`): fast to write and read, the size of the data.
    Stored,
    /// Deflated (`numpy.savez_compressed`): for files that travel.
    Deflated,
}

/// Named arrays as the bytes of an `.npz` (readable by `numpy.load`); errors name the array.
pub fn encode_npz(
    arrays: &[(&str, &[usize], NpyValues<'_>)],
    entries: NpzEntries,
) -> Result<Vec<u8>, String> {
    let mut buf = Cursor::new(Vec::new());
    {
        let mut zip = zip::ZipWriter::new(&mut buf);
        // A fixed timestamp (the zip epoch, 1980-01-01) instead of the current time, so the
        // same arrays always give the same bytes (checkpoints can be verified by hash).
        let method = match entries {
            NpzEntries::Stored => zip::CompressionMethod::Stored,
            NpzEntries::Deflated => zip::CompressionMethod::Deflated,
        };
        let options = zip::write::FileOptions::default()
            .compression_method(method)
            .last_modified_time(zip::DateTime::default());
        for (name, shape, values) in arrays {
            zip.start_file(format!("{name}.npy"), options)
                .map_err(|e| e.to_string())?;
            let bytes = match values {
                NpyValues::F32(v) => encode_npy(shape, v),
                NpyValues::I64(v) => encode_npy(shape, v),
            }
            .map_err(|e| format!("`{name}`: {e}"))?;
            zip.write_all(&bytes).map_err(|e| e.to_string())?;
        }
        zip.finish().map_err(|e| e.to_string())?;
    }
    Ok(buf.into_inner())
}

/// Writes named arrays as an uncompressed `.npz` (readable by `numpy.load`), atomically.
pub fn write_npz(path: &Path, arrays: &[(&str, &[usize], NpyValues<'_>)]) -> Result<(), IoError> {
    let bytes = encode_npz(arrays, NpzEntries::Stored).map_err(|e| IoError::new(path, e))?;
    write_atomic(path, &bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn to_u8_rounds_as_round_does() {
        let reference = |v: f32| (v.clamp(0.0, 1.0) * 255.0).round() as u8;
        // Every half-way point and the floats either side of it, where truncation and
        // rounding part; the ends and what lies beyond them.
        for k in 0..=256u32 {
            let half = (k as f32 - 0.5) / 255.0;
            let mut v = half;
            for _ in 0..4 {
                v = v.next_down();
            }
            for _ in 0..9 {
                assert_eq!(to_u8(v), reference(v), "{v:e}");
                v = v.next_up();
            }
        }
        for v in [
            -1.0,
            -0.0,
            0.0,
            1.0,
            2.0,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
        ] {
            assert_eq!(to_u8(v), reference(v), "{v}");
        }
        // And a dense sweep of [0, 1].
        for i in 0..=1_000_000u32 {
            let v = i as f32 / 1_000_000.0;
            assert_eq!(to_u8(v), reference(v), "{v:e}");
        }
    }

    #[test]
    fn long_inputs_are_quoted_cut() {
        assert_eq!(quoted("abc"), "`abc`");
        let long = "é".repeat(5 << 20);
        let q = quoted(&long);
        assert!(q.chars().count() < QUOTE_CHARS + 40, "{}", q.len());
        assert!(q.ends_with(&format!("({} bytes)", long.len())));
    }

    #[test]
    fn npz_bytes_do_not_depend_on_the_time_of_writing() {
        let dir = tempfile::tempdir().unwrap();
        let (a, b) = (dir.path().join("a.npz"), dir.path().join("b.npz"));
        let values = [1.0f32, 2.0, 3.0];
        let arrays = [("x", &[3][..], NpyValues::F32(&values))];
        write_npz(&a, &arrays).unwrap();
        // The zip format stores times in 2-second steps: cross at least one step.
        std::thread::sleep(std::time::Duration::from_millis(2100));
        write_npz(&b, &arrays).unwrap();
        assert_eq!(std::fs::read(&a).unwrap(), std::fs::read(&b).unwrap());
    }

    #[cfg(unix)]
    #[test]
    fn atomic_writes_get_the_mode_of_a_plain_write() {
        use std::os::unix::fs::PermissionsExt;
        let dir = tempfile::tempdir().unwrap();
        let mode = |p: &Path| std::fs::metadata(p).unwrap().permissions().mode() & 0o777;
        let plain = dir.path().join("plain.txt");
        std::fs::write(&plain, b"x").unwrap();
        let atomic = dir.path().join("atomic.txt");
        write_atomic(&atomic, b"x").unwrap();
        assert_eq!(mode(&atomic), mode(&plain));
        // Rewriting keeps it so (the rename replaces the file, not its mode bits).
        write_atomic(&atomic, b"y").unwrap();
        assert_eq!(mode(&atomic), mode(&plain));
        // Under the usual umask 022 a plain write gives 0644, so a file that kept the
        // temporary file's 0600 fails the first comparison.
    }

    #[test]
    fn png_round_trip_and_size() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.png");
        let data: Vec<f32> = (0..5 * 3 * 3).map(|i| (i % 256) as f32 / 255.0).collect();
        let img = Image::from_vec(5, 3, 3, data).unwrap();
        write_png(&path, &img).unwrap();
        assert_eq!(read_rgb(&path).unwrap(), img);
        assert_eq!(image_size(&path).unwrap(), (5, 3));
        let gray = read_gray(&path).unwrap();
        assert_eq!((gray.width, gray.height, gray.channels), (5, 3, 1));
    }

    #[test]
    fn jpeg_round_trip_is_close_and_too_wide_an_image_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        // A smooth colour gradient (what JPEG keeps well) of a size that is not a multiple of
        // the 8 × 8 blocks.
        let (w, h) = (37, 21);
        let data: Vec<f32> = (0..w * h * 3)
            .map(|i| {
                let (x, y, c) = ((i / 3) % w, (i / 3) / w, i % 3);
                (x as f32 / w as f32 + y as f32 / h as f32 + c as f32 * 0.3).fract()
            })
            .collect();
        let img = Image::from_vec(w, h, 3, data).unwrap();
        for channels in [3, 1] {
            let img = if channels == 1 {
                Image::from_vec(w, h, 1, img.data.iter().step_by(3).copied().collect()).unwrap()
            } else {
                img.clone()
            };
            let path = dir.path().join(format!("a{channels}.jpg"));
            write_jpeg(&path, &img, 95).unwrap();
            let back = if channels == 1 {
                read_gray(&path).unwrap()
            } else {
                read_rgb(&path).unwrap()
            };
            assert_eq!((back.width, back.height, back.channels), (w, h, channels));
            let mean_error = back
                .data
                .iter()
                .zip(&img.data)
                .map(|(a, b)| (a - b).abs())
                .sum::<f32>()
                / img.data.len() as f32;
            assert!(mean_error < 0.02, "{channels} channels: {mean_error}");
        }
        let wide = Image::filled(70_000, 1, 1, 0.5);
        let error = write_jpeg(&dir.path().join("wide.jpg"), &wide, 95).unwrap_err();
        assert!(error.to_string().contains("65 535"), "{error}");
        assert!(!dir.path().join("wide.jpg").exists());
    }

    #[test]
    fn npy_round_trip() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.npy");
        let data: Vec<f32> = (0..24).map(|i| i as f32 * 0.5).collect();
        write_npy_f32(&path, &[2, 3, 4], &data).unwrap();
        assert_eq!(read_npy_f32(&path).unwrap(), (vec![2, 3, 4], data));
        assert_eq!(
            encode_npy_f32(&[2, 2], &[1.0]).unwrap_err(),
            "1 values for shape [2, 2]"
        );
    }

    #[test]
    fn npz_round_trip_and_missing_arrays() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.npz");
        write_npz(
            &path,
            &[
                ("x", &[2, 2], NpyValues::F32(&[1.0, 2.0, 3.0, 4.0])),
                ("y", &[1], NpyValues::F32(&[5.0])),
                ("k", &[2], NpyValues::I64(&[-1, 7])),
            ],
        )
        .unwrap();
        let mut npz = Npz::open(&path).unwrap();
        assert!(npz.contains("x") && npz.contains("y"));
        assert_eq!(
            npz.f32("x").unwrap(),
            (vec![2, 2], vec![1.0, 2.0, 3.0, 4.0])
        );
        let e = npz.f32("z").unwrap_err().to_string();
        assert!(
            e.contains("a.npz") && e.contains("missing array `z`"),
            "{e}"
        );
        let e = npz.i64("y").unwrap_err().to_string();
        assert!(e.contains("not an integer type"), "{e}");
        assert_eq!(npz.i64("k").unwrap(), (vec![2], vec![-1, 7]));
    }

    #[test]
    fn unreadable_files_name_the_path() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("broken.jpg");
        std::fs::write(&path, b"\xff\xd8\xff\xe0 truncated").unwrap();
        let e = read_rgb(&path).unwrap_err().to_string();
        assert!(e.contains("broken.jpg"), "{e}");
        let e = read_rgb(&dir.path().join("missing.png"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("missing.png"), "{e}");
    }

    #[test]
    fn clearing_outputs_removes_only_what_the_command_owns() {
        let dir = tempfile::tempdir().unwrap();
        for name in ["frame_00000.png", "frame_00001.png", "notes.txt"] {
            std::fs::write(dir.path().join(name), b"x").unwrap();
        }
        std::fs::create_dir(dir.path().join("cam00")).unwrap();
        std::fs::write(dir.path().join("cam00/a.jpg"), b"x").unwrap();
        let owned = |n: &str, is_dir: bool| n.starts_with("frame_") || (is_dir && n == "cam00");
        assert_eq!(clear_outputs(dir.path(), owned).unwrap(), 3);
        let left: Vec<_> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(left, ["notes.txt"]);
        assert_eq!(clear_outputs(&dir.path().join("none"), owned).unwrap(), 0);
    }

    #[test]
    fn an_atomic_write_into_a_missing_folder_names_the_folder() {
        let dir = tempfile::tempdir().unwrap();
        let missing = dir.path().join("not-made");
        let error = write_atomic(&missing.join("a.glb"), b"x").unwrap_err();
        let message = error.to_string();
        assert!(message.contains("a.glb"), "{message}");
        assert!(
            message.contains(&format!("the folder {} does not exist", missing.display())),
            "{message}"
        );
    }

    #[test]
    fn atomic_write_replaces_and_leaves_no_temporary_files() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("out.bin");
        write_atomic(&path, b"first").unwrap();
        write_atomic(&path, b"second").unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), b"second");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }
}
