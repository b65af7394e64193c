//! Reading and writing images: OpenEXR (through `exr`), PNG/JPEG and Radiance
//! HDR (through `image`). Every write goes to a temporary file in the target
//! folder and is renamed into place, so a crash never leaves half a file.

use std::io::{Cursor, Write};
use std::path::{Path, PathBuf};

use exr::prelude as x;
use exr::prelude::{ReadChannels, ReadLayers};
use glam::Vec3;
use image::{ImageFormat, Rgb};

use crate::color;
use crate::error::{Result, SceneError};
use crate::image::{count_non_finite, GrayImage, Image, RgbImage};

/// Largest image side matflow accepts; anything bigger is treated as corrupt.
pub const MAX_SIDE: usize = 1 << 14;

/// A temporary sibling name for writing `name`: hidden, and unique across
/// hosts sharing a folder, processes and concurrent writers in one
/// process (host name, process id and a random part), so two writers of
/// one path never share a temporary file.
pub fn temp_name(name: &str) -> String {
    use std::hash::{BuildHasher, Hasher};
    use std::sync::atomic::{AtomicU64, Ordering};
    static COUNTER: AtomicU64 = AtomicU64::new(0);
    let host = std::fs::read_to_string("/proc/sys/kernel/hostname")
        .ok()
        .or_else(|| std::env::var("HOSTNAME").ok())
        .map(|h| {
            h.trim()
                .chars()
                .filter(|c| c.is_ascii_alphanumeric() || *c == '-')
                .take(32)
                .collect::<String>()
        })
        .filter(|h| !h.is_empty())
        .unwrap_or_else(|| "host".into());
    // Randomly keyed per process by the standard library; the counter and
    // clock separate writers within it.
    let mut h = std::collections::hash_map::RandomState::new().build_hasher();
    h.write_u64(COUNTER.fetch_add(1, Ordering::Relaxed));
    h.write_u128(
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos()),
    );
    format!(
        ".{name}.tmp-{host}-{}-{:016x}",
        std::process::id(),
        h.finish()
    )
}

/// Writes `bytes` to `path` unless the file already holds exactly these
/// bytes (then it is left alone: not rewritten, its time stamps kept).
/// Returns whether it wrote.
pub fn write_if_changed(path: &Path, bytes: &[u8]) -> Result<bool> {
    if let Ok(meta) = std::fs::metadata(path) {
        if meta.is_file() && meta.len() == bytes.len() as u64 {
            if let Ok(old) = std::fs::read(path) {
                if old == bytes {
                    return Ok(false);
                }
            }
        }
    }
    write_atomic(path, bytes)?;
    Ok(true)
}

/// Writes `bytes` to `path` atomically (temporary sibling + rename).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    let dir = path
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    std::fs::create_dir_all(dir).map_err(|e| SceneError::io(dir, e))?;
    let name = path
        .file_name()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "out".into());
    let tmp: PathBuf = dir.join(temp_name(&name));
    let res = (|| -> std::io::Result<()> {
        let mut f = std::fs::File::create(&tmp)?;
        f.write_all(bytes)?;
        f.sync_all()?;
        std::fs::rename(&tmp, path)
    })();
    if let Err(e) = res {
        let _ = std::fs::remove_file(&tmp);
        return Err(SceneError::io(path, e));
    }
    Ok(())
}

fn read_bytes(path: &Path) -> Result<Vec<u8>> {
    std::fs::read(path).map_err(|e| SceneError::io(path, e))
}

fn check_size(path: &Path, w: usize, h: usize) -> Result<()> {
    if w == 0 || h == 0 || w > MAX_SIDE || h > MAX_SIDE {
        return Err(SceneError::invalid(
            path,
            format!("implausible image size {w}x{h} (each side must be 1..={MAX_SIDE})"),
        ));
    }
    Ok(())
}

/// All channels of the first layer of an EXR file, as f32 planes keyed by
/// channel name (e.g. "R", "G", "B", "Y").
pub struct ExrChannels {
    pub width: usize,
    pub height: usize,
    pub channels: Vec<(String, Vec<f32>)>,
}

impl ExrChannels {
    pub fn get(&self, name: &str) -> Option<&[f32]> {
        self.channels
            .iter()
            .find(|(n, _)| n == name)
            .map(|(_, v)| v.as_slice())
    }
}

/// Size (width, height) of an EXR's first layer, from its header alone.
pub fn exr_size(path: &Path) -> Result<(usize, usize)> {
    exr_size_of(path, &read_bytes(path)?)
}

fn exr_size_of(path: &Path, bytes: &[u8]) -> Result<(usize, usize)> {
    let meta = exr_meta(path, bytes)?;
    let h = meta
        .headers
        .first()
        .ok_or_else(|| SceneError::invalid(path, "no image layer"))?;
    Ok((h.layer_size.0, h.layer_size.1))
}

fn exr_meta(path: &Path, bytes: &[u8]) -> Result<exr::meta::MetaData> {
    exr::meta::MetaData::read_from_buffered(Cursor::new(bytes), false).map_err(|e| {
        SceneError::Decode {
            path: path.into(),
            message: e.to_string(),
        }
    })
}

/// Checks an EXR's headers before any pixel is decoded: every layer at
/// most [`MAX_SIDE`] a side, at most 16 channels, and no more pixel bytes
/// than its file could hold compressed (2,048 : 1, beyond any codec's
/// ratio on real images, plus 16 MiB). The decoder allocates a layer's
/// whole buffer from its header, so a few hundred forged bytes could
/// otherwise ask for gigabytes (found by tests/fuzz.rs).
fn check_exr_header(path: &Path, bytes: &[u8]) -> Result<()> {
    let meta = exr_meta(path, bytes)?;
    let budget = (bytes.len() as u64).saturating_mul(2048) + (16 << 20);
    for h in meta.headers.iter() {
        let (w, ht) = (h.layer_size.0, h.layer_size.1);
        if w > MAX_SIDE || ht > MAX_SIDE {
            return Err(SceneError::invalid(
                path,
                format!("implausible image size {w}x{ht} (each side must be 1..={MAX_SIDE})"),
            ));
        }
        if h.channels.list.len() > 16 {
            return Err(SceneError::invalid(
                path,
                format!(
                    "{} channels (matflow reads at most 16)",
                    h.channels.list.len()
                ),
            ));
        }
        let raw = (w as u64) * (ht as u64) * (h.channels.bytes_per_pixel as u64);
        if raw > budget {
            return Err(SceneError::invalid(
                path,
                format!(
                    "the header declares {w}x{ht} pixels ({raw} bytes), more than a {}-byte file can hold",
                    bytes.len()
                ),
            ));
        }
    }
    Ok(())
}

pub fn read_exr_channels(path: &Path) -> Result<ExrChannels> {
    exr_channels_of(path, read_bytes(path)?)
}

/// [`read_exr_channels`] of a file already read (`path` names it in
/// errors).
fn exr_channels_of(path: &Path, bytes: Vec<u8>) -> Result<ExrChannels> {
    check_exr_header(path, &bytes)?;
    let img = x::read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .first_valid_layer()
        .all_attributes()
        .from_buffered(Cursor::new(bytes))
        .map_err(|e| SceneError::Decode {
            path: path.into(),
            message: e.to_string(),
        })?;
    let layer = img.layer_data;
    let (w, h) = (layer.size.0, layer.size.1);
    check_size(path, w, h)?;
    let channels = layer
        .channel_data
        .list
        .iter()
        .map(|c| {
            (
                c.name.to_string(),
                c.sample_data.values_as_f32().collect::<Vec<f32>>(),
            )
        })
        .collect::<Vec<_>>();
    for (name, v) in &channels {
        if v.len() != w * h {
            return Err(SceneError::invalid(
                path,
                format!("channel {name} is subsampled, which matflow does not support"),
            ));
        }
    }
    Ok(ExrChannels {
        width: w,
        height: h,
        channels,
    })
}

/// Reads an RGB EXR. A single-channel file (`Y` or any one channel) is
/// replicated into RGB.
pub fn read_exr_rgb(path: &Path) -> Result<RgbImage> {
    exr_rgb_of(path, read_exr_channels(path)?)
}

fn exr_rgb_of(path: &Path, c: ExrChannels) -> Result<RgbImage> {
    let (w, h) = (c.width, c.height);
    if let (Some(r), Some(g), Some(b)) = (c.get("R"), c.get("G"), c.get("B")) {
        let data = (0..w * h).map(|i| Vec3::new(r[i], g[i], b[i])).collect();
        return Ok(Image::from_vec(w, h, data));
    }
    if c.channels.len() == 1 || c.get("Y").is_some() {
        let y = c.get("Y").unwrap_or(&c.channels[0].1);
        return Ok(Image::from_vec(w, h, y.to_vec()).to_rgb());
    }
    Err(SceneError::invalid(
        path,
        format!(
            "expected channels R,G,B or a single channel, found {:?}",
            c.channels
                .iter()
                .map(|(n, _)| n.as_str())
                .collect::<Vec<_>>()
        ),
    ))
}

/// Reads a single-channel EXR (`Y`, or the only channel, or the mean of RGB).
pub fn read_exr_gray(path: &Path) -> Result<GrayImage> {
    let c = read_exr_channels(path)?;
    let (w, h) = (c.width, c.height);
    if let Some(y) = c.get("Y") {
        return Ok(Image::from_vec(w, h, y.to_vec()));
    }
    if c.channels.len() == 1 {
        return Ok(Image::from_vec(w, h, c.channels[0].1.clone()));
    }
    let rgb = read_exr_rgb(path)?;
    Ok(rgb.channel(0))
}

fn exr_encoding() -> x::Encoding {
    x::Encoding {
        compression: x::Compression::PIZ,
        blocks: x::Blocks::ScanLines,
        line_order: x::LineOrder::Increasing,
    }
}

fn exr_to_bytes(
    path: &Path,
    image: impl FnOnce(&mut Cursor<Vec<u8>>) -> exr::error::UnitResult,
) -> Result<Vec<u8>> {
    let mut cur = Cursor::new(Vec::new());
    image(&mut cur).map_err(|e| SceneError::Encode {
        path: path.into(),
        message: e.to_string(),
    })?;
    Ok(cur.into_inner())
}

/// Writes linear RGB as a 32-bit float, PIZ-compressed scanline EXR
/// (blocks compressed on all cores, written in line order: the bytes do
/// not depend on the thread count).
pub fn write_exr_rgb(path: &Path, img: &RgbImage) -> Result<()> {
    write_atomic(path, &encode_exr_rgb(path, img)?)
}

/// The bytes [`write_exr_rgb`] writes (`path` names the file in errors).
pub fn encode_exr_rgb(path: &Path, img: &RgbImage) -> Result<Vec<u8>> {
    let w = img.width;
    let channels = x::SpecificChannels::rgb(|p: x::Vec2<usize>| {
        let v = img.data[p.1 * w + p.0];
        (v.x, v.y, v.z)
    });
    let image = x::Image::from_encoded_channels((img.width, img.height), exr_encoding(), channels);
    exr_to_bytes(path, |c| {
        use x::WritableImage;
        image.write().to_buffered(c)
    })
}

/// Writes one float channel named `Y` (the reference's layout for depth).
pub fn write_exr_gray(path: &Path, img: &GrayImage) -> Result<()> {
    write_atomic(path, &encode_exr_gray(path, img)?)
}

/// The bytes [`write_exr_gray`] writes (`path` names the file in errors).
pub fn encode_exr_gray(path: &Path, img: &GrayImage) -> Result<Vec<u8>> {
    let chan = x::AnyChannel::new("Y", x::FlatSamples::F32(img.data.clone()));
    let channels = x::AnyChannels::sort(smallvec_one(chan));
    let image = x::Image::from_encoded_channels((img.width, img.height), exr_encoding(), channels);
    exr_to_bytes(path, |c| {
        use x::WritableImage;
        image.write().to_buffered(c)
    })
}

fn smallvec_one<T>(v: T) -> x::SmallVec<[T; 4]> {
    let mut s = x::SmallVec::new();
    s.push(v);
    s
}

/// Reads a Radiance HDR file. Files whose magic line is `#?RGBE` (as the
/// reference writes them) are accepted as well as `#?RADIANCE`.
pub fn read_hdr(path: &Path) -> Result<RgbImage> {
    let mut bytes = read_bytes(path)?;
    if bytes.starts_with(b"#?RGBE\n") {
        let mut fixed = b"#?RADIANCE\n".to_vec();
        fixed.extend_from_slice(&bytes[7..]);
        bytes = fixed;
    }
    let img = image::load_from_memory_with_format(&bytes, ImageFormat::Hdr).map_err(|e| {
        SceneError::Decode {
            path: path.into(),
            message: e.to_string(),
        }
    })?;
    let rgb = img.to_rgb32f();
    let (w, h) = (rgb.width() as usize, rgb.height() as usize);
    check_size(path, w, h)?;
    let data = rgb.pixels().map(|p| Vec3::new(p[0], p[1], p[2])).collect();
    Ok(Image::from_vec(w, h, data))
}

/// Writes a Radiance HDR file (`#?RADIANCE`, RLE RGBE). Negative and
/// non-finite values are written as 0.
pub fn write_hdr(path: &Path, img: &RgbImage) -> Result<()> {
    write_atomic(path, &encode_hdr(path, img)?)
}

/// The bytes [`write_hdr`] writes (`path` names the file in errors).
pub fn encode_hdr(path: &Path, img: &RgbImage) -> Result<Vec<u8>> {
    let px: Vec<Rgb<f32>> = img
        .data
        .iter()
        .map(|v| {
            let f = |c: f32| if c.is_finite() { c.max(0.0) } else { 0.0 };
            Rgb([f(v.x), f(v.y), f(v.z)])
        })
        .collect();
    let mut buf = Vec::new();
    image::codecs::hdr::HdrEncoder::new(&mut buf)
        .encode(&px, img.width, img.height)
        .map_err(|e| SceneError::Encode {
            path: path.into(),
            message: e.to_string(),
        })?;
    Ok(buf)
}

/// Reads an 8- or 16-bit PNG/JPEG as RGB values in [0, 1] (no transfer
/// function applied). Gray and alpha channels are expanded/dropped.
pub fn read_ldr_raw(path: &Path) -> Result<RgbImage> {
    let bytes = read_bytes(path)?;
    let img = image::load_from_memory(&bytes).map_err(|e| SceneError::Decode {
        path: path.into(),
        message: e.to_string(),
    })?;
    let (w, h) = (img.width() as usize, img.height() as usize);
    check_size(path, w, h)?;
    let rgb = img.to_rgb32f();
    let data = rgb.pixels().map(|p| Vec3::new(p[0], p[1], p[2])).collect();
    Ok(Image::from_vec(w, h, data))
}

/// Reads a mask PNG: a pixel is set where its largest colour value is above
/// one half and, for images with alpha, its alpha is above one half too.
pub fn read_mask(path: &Path) -> Result<Image<bool>> {
    decode_mask(path, &read_bytes(path)?)
}

/// [`read_mask`] of bytes already read; `path` names them in errors.
pub fn decode_mask(path: &Path, bytes: &[u8]) -> Result<Image<bool>> {
    // The size from the header first: a few bytes can claim a huge image.
    let decode_err = |e: &dyn std::fmt::Display| SceneError::Decode {
        path: path.into(),
        message: e.to_string(),
    };
    let (w, h) = image::ImageReader::new(std::io::Cursor::new(bytes))
        .with_guessed_format()
        .map_err(|e| decode_err(&e))?
        .into_dimensions()
        .map_err(|e| decode_err(&e))?;
    check_size(path, w as usize, h as usize)?;
    let img = image::load_from_memory(bytes).map_err(|e| SceneError::Decode {
        path: path.into(),
        message: e.to_string(),
    })?;
    let (w, h) = (img.width() as usize, img.height() as usize);
    check_size(path, w, h)?;
    let has_alpha = img.color().has_alpha();
    let rgba = img.to_rgba32f();
    let data = rgba
        .pixels()
        .map(|p| {
            let c = p[0].max(p[1]).max(p[2]) > 0.5;
            if has_alpha {
                c && p[3] > 0.5
            } else {
                c
            }
        })
        .collect();
    Ok(Image::from_vec(w, h, data))
}

/// Encodes linear RGB for display: clip to [0, 1], power 1/2.2, 8 bits (the
/// reference's convention), and writes a PNG.
pub fn write_png_gamma(path: &Path, img: &RgbImage) -> Result<()> {
    write_atomic(path, &encode_png_gamma(path, img)?)
}

/// The bytes [`write_png_gamma`] writes (`path` names the file in errors).
pub fn encode_png_gamma(path: &Path, img: &RgbImage) -> Result<Vec<u8>> {
    let mut out = image::RgbImage::new(img.width as u32, img.height as u32);
    for (o, v) in out.pixels_mut().zip(img.data.iter()) {
        let g = color::linear_to_gamma3(*v);
        *o = Rgb([color::to_u8(g.x), color::to_u8(g.y), color::to_u8(g.z)]);
    }
    let mut buf = Cursor::new(Vec::new());
    out.write_to(&mut buf, ImageFormat::Png)
        .map_err(|e| SceneError::Encode {
            path: path.into(),
            message: e.to_string(),
        })?;
    Ok(buf.into_inner())
}

/// Linear RGB as an 8-bit sRGB PNG in memory (clipped to [0, 1]): how a
/// dataset stores its photographs.
pub fn png_srgb_bytes(img: &RgbImage) -> Result<Vec<u8>> {
    let mut out = image::RgbImage::new(img.width as u32, img.height as u32);
    for (o, v) in out.pixels_mut().zip(img.data.iter()) {
        let f = |c: f32| color::to_u8(color::linear_to_srgb(c.clamp(0.0, 1.0)));
        *o = Rgb([f(v.x), f(v.y), f(v.z)]);
    }
    png_in_memory(out)
}

/// An 8-bit image as PNG bytes.
fn png_in_memory<P, C>(img: image::ImageBuffer<P, C>) -> Result<Vec<u8>>
where
    P: image::PixelWithColorType,
    [P::Subpixel]: image::EncodableLayout,
    C: std::ops::Deref<Target = [P::Subpixel]>,
{
    let mut buf = Cursor::new(Vec::new());
    img.write_to(&mut buf, ImageFormat::Png)
        .map_err(|e| SceneError::Encode {
            path: "(a PNG in memory)".into(),
            message: e.to_string(),
        })?;
    Ok(buf.into_inner())
}

/// A mask as an 8-bit grey PNG in memory: 255 inside, 0 outside.
pub fn png_mask_bytes(mask: &Image<bool>) -> Result<Vec<u8>> {
    let out = image::GrayImage::from_fn(mask.width as u32, mask.height as u32, |x, y| {
        image::Luma([if mask.get(x as usize, y as usize) {
            255
        } else {
            0
        }])
    });
    let mut buf = Cursor::new(Vec::new());
    out.write_to(&mut buf, ImageFormat::Png)
        .map_err(|e| SceneError::Encode {
            path: "(a PNG in memory)".into(),
            message: e.to_string(),
        })?;
    Ok(buf.into_inner())
}

/// Writes a map in [0, 1] (roughness, metallic) as an 8-bit PNG through the
/// sRGB curve, as Mitsuba's bitmap writer did for the reference's `*Pred.png`.
pub fn write_png_srgb_map(path: &Path, img: &GrayImage) -> Result<()> {
    let mut out = image::RgbImage::new(img.width as u32, img.height as u32);
    for (o, &v) in out.pixels_mut().zip(img.data.iter()) {
        let b = color::to_u8(color::linear_to_srgb(v));
        *o = Rgb([b, b, b]);
    }
    let mut buf = Cursor::new(Vec::new());
    out.write_to(&mut buf, ImageFormat::Png)
        .map_err(|e| SceneError::Encode {
            path: path.into(),
            message: e.to_string(),
        })?;
    write_atomic(path, buf.get_ref())
}

/// Smallest and largest environment map accepted (width, height).
pub const ENVMAP_MIN: (usize, usize) = (2, 2);
pub const ENVMAP_MAX: (usize, usize) = (16384, 8192);

/// Reads a lat-long environment map, Radiance HDR or linear EXR (the
/// same formats wherever an envmap is given), and checks what a light
/// source needs: a size in [`ENVMAP_MIN`]..=[`ENVMAP_MAX`], finite and
/// non-negative radiance.
pub fn read_envmap(path: &Path) -> Result<RgbImage> {
    let ext = path
        .extension()
        .map(|e| e.to_string_lossy().to_lowercase())
        .unwrap_or_default();
    let img = match ext.as_str() {
        "hdr" => read_hdr(path)?,
        "exr" => read_exr_rgb(path)?,
        _ => {
            return Err(SceneError::invalid(
                path,
                "an environment map must be Radiance HDR (.hdr) or linear OpenEXR (.exr)",
            ))
        }
    };
    check_envmap(path, &img)?;
    Ok(img)
}

/// The checks of [`read_envmap`] on an image already in memory (`path`
/// names it in errors).
pub fn check_envmap(path: &Path, img: &RgbImage) -> Result<()> {
    if img.width < ENVMAP_MIN.0
        || img.height < ENVMAP_MIN.1
        || img.width > ENVMAP_MAX.0
        || img.height > ENVMAP_MAX.1
    {
        return Err(SceneError::invalid(
            path,
            format!(
                "an environment map of {}x{} is out of range ({}x{} to {}x{})",
                img.width, img.height, ENVMAP_MIN.0, ENVMAP_MIN.1, ENVMAP_MAX.0, ENVMAP_MAX.1
            ),
        ));
    }
    ensure_finite_rgb(path, img)?;
    if let Some(i) = img.data.iter().position(|v| v.min_element() < 0.0) {
        return Err(SceneError::invalid(
            path,
            format!(
                "negative radiance {:?} at x={}, y={} (an environment map emits light >= 0)",
                img.data[i].to_array(),
                i % img.width,
                i / img.width
            ),
        ));
    }
    Ok(())
}

/// Rejects images holding NaN or Inf, naming the file and the pixel count.
pub fn ensure_finite_rgb(path: &Path, img: &RgbImage) -> Result<()> {
    let (count, (x, y)) = count_non_finite(img, |v: Vec3| v.is_finite());
    if count > 0 {
        return Err(SceneError::NonFinite {
            path: path.into(),
            count,
            x,
            y,
        });
    }
    Ok(())
}

pub fn ensure_finite_gray(path: &Path, img: &GrayImage) -> Result<()> {
    let (count, (x, y)) = count_non_finite(img, |v: f32| v.is_finite());
    if count > 0 {
        return Err(SceneError::NonFinite {
            path: path.into(),
            count,
            x,
            y,
        });
    }
    Ok(())
}

/// Centre-crops to a square and resizes to `size`×`size` (bilinear, on the
/// encoded values), then linearises with power 2.2 as the reference does.
pub fn load_photo(path: &Path, size: usize) -> Result<RgbImage> {
    let raw = read_ldr_raw(path)?;
    Ok(prepare_photo(&raw, size).map(|v| {
        Vec3::new(
            color::gamma_to_linear(v.x),
            color::gamma_to_linear(v.y),
            color::gamma_to_linear(v.z),
        )
    }))
}

/// Centre crop to a square, then resize to `size`×`size` with bilinear
/// (area-aware when shrinking) filtering.
pub fn prepare_photo(img: &RgbImage, size: usize) -> RgbImage {
    let side = img.width.min(img.height);
    let x0 = (img.width - side) / 2;
    let y0 = (img.height - side) / 2;
    let crop = Image::from_fn(side, side, |x, y| img.get(x + x0, y + y0));
    if side == size {
        return crop;
    }
    resize_bilinear(&crop, size, size)
}

/// Bilinear resize with pixel-centre alignment (as OpenCV's INTER_LINEAR),
/// prefiltered with a box when shrinking by more than 2× to avoid aliasing.
pub fn resize_bilinear(img: &RgbImage, w: usize, h: usize) -> RgbImage {
    let mut src = img.clone();
    while src.width >= 2 * w && src.height >= 2 * h {
        src = Image::from_fn(src.width / 2, src.height / 2, |x, y| {
            (src.get(2 * x, 2 * y)
                + src.get(2 * x + 1, 2 * y)
                + src.get(2 * x, 2 * y + 1)
                + src.get(2 * x + 1, 2 * y + 1))
                * 0.25
        });
    }
    let sx = src.width as f32 / w as f32;
    let sy = src.height as f32 / h as f32;
    Image::from_fn(w, h, |x, y| {
        let fx = ((x as f32 + 0.5) * sx - 0.5).clamp(0.0, src.width as f32 - 1.0);
        let fy = ((y as f32 + 0.5) * sy - 0.5).clamp(0.0, src.height as f32 - 1.0);
        let x0 = fx.floor() as usize;
        let y0 = fy.floor() as usize;
        let x1 = (x0 + 1).min(src.width - 1);
        let y1 = (y0 + 1).min(src.height - 1);
        let tx = fx - x0 as f32;
        let ty = fy - y0 as f32;
        let a = src.get(x0, y0) * (1.0 - tx) + src.get(x1, y0) * tx;
        let b = src.get(x0, y1) * (1.0 - tx) + src.get(x1, y1) * tx;
        a * (1.0 - ty) + b * ty
    })
}

/// The most pixels a photo given to a prediction stage may have (a
/// 100-megapixel photo is read; larger ones are refused before decoding).
pub const MAX_PHOTO_PIXELS: usize = 150_000_000;

/// A photo's pixels as stored: 8- or 16-bit display-encoded samples
/// (interleaved, `channels` per pixel: 1 grey, 2 grey + alpha, 3 RGB, 4
/// RGBA) or linear RGB from an EXR.
pub enum PhotoPixels {
    U8 { channels: usize, data: Vec<u8> },
    U16 { channels: usize, data: Vec<u16> },
    Linear(RgbImage),
}

pub struct Photo {
    pub width: usize,
    pub height: usize,
    pub pixels: PhotoPixels,
}

impl Photo {
    /// Channel `ch` (0–2) at (`y`, `x`): 0–255 for 8-bit samples, /257
    /// for 16-bit ones (the same scale), linear radiance for EXR. Grey is
    /// read as R = G = B; alpha is ignored.
    #[inline]
    pub fn at(&self, ch: usize, y: usize, x: usize) -> f32 {
        let i = y * self.width + x;
        match &self.pixels {
            PhotoPixels::U8 { channels, data } => {
                let c = if *channels >= 3 { ch } else { 0 };
                data[i * channels + c] as f32
            }
            PhotoPixels::U16 { channels, data } => {
                let c = if *channels >= 3 { ch } else { 0 };
                data[i * channels + c] as f32 / 257.0
            }
            PhotoPixels::Linear(img) => img.data[i][ch],
        }
    }
    pub fn is_linear(&self) -> bool {
        matches!(self.pixels, PhotoPixels::Linear(_))
    }
    /// What was converted on reading, for the record (empty when
    /// nothing).
    pub fn conversions(&self) -> Vec<&'static str> {
        let mut v = vec![];
        match &self.pixels {
            PhotoPixels::U8 { channels, .. } | PhotoPixels::U16 { channels, .. } => {
                if *channels <= 2 {
                    v.push("grey replicated to RGB");
                }
                if *channels == 2 || *channels == 4 {
                    v.push("alpha ignored");
                }
                if matches!(self.pixels, PhotoPixels::U16 { .. }) {
                    v.push("16-bit samples scaled to 0-255 (/257, not rounded)");
                }
            }
            PhotoPixels::Linear(_) => v.push("EXR read as linear RGB"),
        }
        v
    }
}

fn is_exr(bytes: &[u8]) -> bool {
    bytes.starts_with(&[0x76, 0x2f, 0x31, 0x01])
}

fn image_reader<'a>(path: &Path, bytes: &'a [u8]) -> Result<image::ImageReader<Cursor<&'a [u8]>>> {
    image::ImageReader::new(Cursor::new(bytes))
        .with_guessed_format()
        .map_err(|e| SceneError::io(path, e))
}

/// A photo's size from its header, refused past [`MAX_PHOTO_PIXELS`]
/// (nothing is decoded): what [`read_photo`] checks first.
pub fn photo_size(path: &Path) -> Result<(usize, usize)> {
    photo_size_of(path, &read_bytes(path)?)
}

fn photo_size_of(path: &Path, bytes: &[u8]) -> Result<(usize, usize)> {
    let (w, h) = if is_exr(bytes) {
        exr_size_of(path, bytes)?
    } else {
        let (w, h) =
            image_reader(path, bytes)?
                .into_dimensions()
                .map_err(|e| SceneError::Decode {
                    path: path.into(),
                    message: e.to_string(),
                })?;
        (w as usize, h as usize)
    };
    check_size(path, w, h)?;
    if w * h > MAX_PHOTO_PIXELS {
        return Err(SceneError::invalid(
            path,
            format!(
                "the photo is {w}x{h} = {:.1} megapixels, more than the {} megapixels matflow \
                 reads; scale it down first",
                (w * h) as f64 / 1e6,
                MAX_PHOTO_PIXELS / 1_000_000
            ),
        ));
    }
    Ok((w, h))
}

/// Reads a photo (PNG or JPEG of 8 or 16 bits, grey or colour, with or
/// without alpha; or an EXR, linear RGB or one channel). Refused with the
/// reason: undecodable files, more than [`MAX_PHOTO_PIXELS`] (checked from
/// the header, before decoding), and EXRs holding NaN, infinities or
/// negative values.
pub fn read_photo(path: &Path) -> Result<Photo> {
    let bytes = read_bytes(path)?;
    let (w, h) = photo_size_of(path, &bytes)?;
    if is_exr(&bytes) {
        let img = exr_rgb_of(path, exr_channels_of(path, bytes)?)?;
        for (i, p) in img.data.iter().enumerate() {
            if !p.is_finite() || p.min_element() < 0.0 {
                return Err(SceneError::invalid(
                    path,
                    format!(
                        "pixel x={}, y={} is ({}, {}, {}): a photo must hold finite, \
                         non-negative radiance",
                        i % w,
                        i / w,
                        p.x,
                        p.y,
                        p.z
                    ),
                ));
            }
        }
        return Ok(Photo {
            width: w,
            height: h,
            pixels: PhotoPixels::Linear(img),
        });
    }
    let decode = |e: image::ImageError| SceneError::Decode {
        path: path.into(),
        message: e.to_string(),
    };
    let mut r = image_reader(path, &bytes)?;
    let mut limits = image::Limits::default();
    limits.max_alloc = Some(4 << 30);
    r.limits(limits);
    let img = r.decode().map_err(decode)?;
    use image::DynamicImage as D;
    let pixels = match img {
        D::ImageLuma8(b) => PhotoPixels::U8 {
            channels: 1,
            data: b.into_raw(),
        },
        D::ImageLumaA8(b) => PhotoPixels::U8 {
            channels: 2,
            data: b.into_raw(),
        },
        D::ImageRgb8(b) => PhotoPixels::U8 {
            channels: 3,
            data: b.into_raw(),
        },
        D::ImageRgba8(b) => PhotoPixels::U8 {
            channels: 4,
            data: b.into_raw(),
        },
        D::ImageLuma16(b) => PhotoPixels::U16 {
            channels: 1,
            data: b.into_raw(),
        },
        D::ImageLumaA16(b) => PhotoPixels::U16 {
            channels: 2,
            data: b.into_raw(),
        },
        D::ImageRgb16(b) => PhotoPixels::U16 {
            channels: 3,
            data: b.into_raw(),
        },
        D::ImageRgba16(b) => PhotoPixels::U16 {
            channels: 4,
            data: b.into_raw(),
        },
        other => PhotoPixels::U8 {
            channels: 3,
            data: other.to_rgb8().into_raw(),
        },
    };
    Ok(Photo {
        width: w,
        height: h,
        pixels,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// EXR blocks are compressed on all cores but written in line order:
    /// the bytes are those of compressing them one after another.
    #[test]
    fn exr_bytes_do_not_depend_on_parallel_compression() {
        let img = Image::from_fn(97, 300, |x, y| {
            let h = ((x * 7919 + y * 104_729) as u32).wrapping_mul(0x9e37_79b9);
            Vec3::new((h >> 20) as f32 / 7.0, (h % 77) as f32, 0.5)
        });
        let w = img.width;
        let channels = x::SpecificChannels::rgb(|p: x::Vec2<usize>| {
            let v = img.data[p.1 * w + p.0];
            (v.x, v.y, v.z)
        });
        let one =
            x::Image::from_encoded_channels((img.width, img.height), exr_encoding(), channels);
        let serial = exr_to_bytes(Path::new("a.exr"), |c| {
            use x::WritableImage;
            one.write().non_parallel().to_buffered(c)
        })
        .unwrap();
        assert_eq!(encode_exr_rgb(Path::new("a.exr"), &img).unwrap(), serial);
        let f = std::env::temp_dir().join(format!("matflow-exrpar-{}.exr", std::process::id()));
        std::fs::write(&f, &serial).unwrap();
        assert_eq!(read_exr_rgb(&f).unwrap().data, img.data);
        let _ = std::fs::remove_file(&f);
    }

    #[test]
    fn an_exr_header_claiming_more_pixels_than_its_file_holds_is_refused_unread() {
        let dir = std::env::temp_dir().join(format!("matflow-exrhdr-{}", std::process::id()));
        let f = dir.join("a.exr");
        let img = Image::from_fn(4, 3, |x, y| Vec3::new(x as f32, y as f32, 1.0));
        write_exr_rgb(&f, &img).unwrap();
        let mut bytes = std::fs::read(&f).unwrap();
        // dataWindow (box2i: xMin, yMin, xMax, yMax) -> 16000 x 16000.
        let at = bytes
            .windows(b"dataWindow\0box2i\0".len())
            .position(|w| w == b"dataWindow\0box2i\0")
            .unwrap()
            + b"dataWindow\0box2i\0".len()
            + 4;
        bytes[at + 8..at + 12].copy_from_slice(&15999i32.to_le_bytes());
        bytes[at + 12..at + 16].copy_from_slice(&15999i32.to_le_bytes());
        std::fs::write(&f, &bytes).unwrap();
        let e = read_exr_rgb(&f).unwrap_err().to_string();
        assert!(
            e.contains("16000x16000") && e.contains("file can hold"),
            "{e}"
        );
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn temporary_names_differ_per_writer_and_name_host_and_process() {
        let a = temp_name("x.exr");
        let b = temp_name("x.exr");
        assert_ne!(a, b);
        assert!(a.starts_with(".x.exr.tmp-"), "{a}");
        assert!(a.contains(&format!("-{}-", std::process::id())), "{a}");
    }

    #[test]
    fn write_if_changed_leaves_identical_files_alone() {
        use std::os::unix::fs::MetadataExt;
        let dir = std::env::temp_dir().join(format!("matflow-wic-{}", std::process::id()));
        let f = dir.join("a.bin");
        assert!(write_if_changed(&f, b"one").unwrap());
        let ino = std::fs::metadata(&f).unwrap().ino();
        assert!(!write_if_changed(&f, b"one").unwrap());
        assert_eq!(std::fs::metadata(&f).unwrap().ino(), ino);
        assert!(write_if_changed(&f, b"two").unwrap());
        assert_eq!(std::fs::read(&f).unwrap(), b"two");
        assert_eq!(
            std::fs::read_dir(&dir).unwrap().count(),
            1,
            "no temporary left"
        );
        let _ = std::fs::remove_dir_all(&dir);
    }

    fn test_rgb(w: usize, h: usize) -> RgbImage {
        Image::from_fn(w, h, |x, y| {
            Vec3::new(
                x as f32 * 0.25,
                y as f32 * 1.5 + 0.001,
                (x * y) as f32 * 100.0,
            )
        })
    }

    #[test]
    fn exr_rgb_round_trip_is_exact() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.exr");
        let img = test_rgb(13, 7);
        write_exr_rgb(&p, &img).unwrap();
        assert_eq!(read_exr_rgb(&p).unwrap(), img);
    }

    #[test]
    fn exr_gray_round_trip_is_exact_and_named_y() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("d.exr");
        let img = Image::from_fn(9, 5, |x, y| x as f32 * 3.25 - y as f32);
        write_exr_gray(&p, &img).unwrap();
        let c = read_exr_channels(&p).unwrap();
        assert!(c.get("Y").is_some());
        assert_eq!(read_exr_gray(&p).unwrap(), img);
    }

    #[test]
    fn hdr_round_trip_within_rgbe_precision() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("e.hdr");
        let img = Image::from_fn(32, 16, |x, y| {
            Vec3::new(0.01 + x as f32, 1000.0 / (1.0 + y as f32), 0.5)
        });
        write_hdr(&p, &img).unwrap();
        let back = read_hdr(&p).unwrap();
        for (a, b) in img.data.iter().zip(back.data.iter()) {
            assert!(
                ((*a - *b).abs() / a.max_element()).max_element() < 0.01,
                "{a} {b}"
            );
        }
        // The reference writes `#?RGBE`; it must be readable too.
        let mut bytes = std::fs::read(&p).unwrap();
        assert!(bytes.starts_with(b"#?RADIANCE\n"));
        bytes.splice(0..11, b"#?RGBE\n".iter().copied());
        std::fs::write(&p, &bytes).unwrap();
        assert_eq!(read_hdr(&p).unwrap(), back);
    }

    #[test]
    fn corrupt_files_give_errors_naming_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("broken.exr");
        std::fs::write(&p, b"not an exr").unwrap();
        let e = read_exr_rgb(&p).unwrap_err().to_string();
        assert!(e.contains("broken.exr"), "{e}");
        let e = read_hdr(&dir.path().join("missing.hdr"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("missing.hdr"), "{e}");
    }

    #[test]
    fn non_finite_is_reported_with_count() {
        let mut img = test_rgb(4, 4);
        img.set(2, 1, Vec3::new(f32::NAN, 0.0, 0.0));
        img.set(3, 3, Vec3::new(0.0, f32::INFINITY, 0.0));
        let e = ensure_finite_rgb(Path::new("albedoPred.exr"), &img)
            .unwrap_err()
            .to_string();
        assert!(e.contains("albedoPred.exr") && e.contains("2 pixel"), "{e}");
    }

    #[test]
    fn photo_is_cropped_resized_and_linearised() {
        let img = Image::from_fn(30, 20, |x, _| {
            Vec3::splat(if !(5..25).contains(&x) { 1.0 } else { 0.5 })
        });
        let out = prepare_photo(&img, 10);
        assert_eq!((out.width, out.height), (10, 10));
        // The bright side bands were cropped away.
        assert!(out.data.iter().all(|v| (v.x - 0.5).abs() < 1e-6));
    }
}
