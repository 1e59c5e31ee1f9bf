//! Files for the simulators: point clouds from `.npy` (float32/float64 `[N, C]`) and
//! KITTI-style `.bin` (little-endian float32 records of C values, C = 4 by default:
//! x, y, z, intensity); images from `.npy` (float, last two axes H and W) and `.png`
//! (8- or 16-bit grey or RGB, with or without alpha). Every error names the file.

use std::io::BufReader;
use std::path::Path;

use image::{DynamicImage, ImageBuffer, ImageFormat, ImageReader};
use ndarray::{ArrayD, IxDyn};
use ndarray_npy::{ReadNpyExt, WriteNpyExt};

use super::lidar::{MAX_COLUMNS, MIN_COLUMNS, PointCloud};

/// The file kinds the simulators read and write, by extension.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Format {
    Npy,
    Bin,
    Png,
}

impl Format {
    /// The format of a path, from its extension (case-insensitive).
    pub fn of(path: &Path) -> Result<Format, String> {
        let ext = path.extension().and_then(|e| e.to_str()).unwrap_or("").to_ascii_lowercase();
        match ext.as_str() {
            "npy" => Ok(Format::Npy),
            "bin" => Ok(Format::Bin),
            "png" => Ok(Format::Png),
            _ => Err(format!(
                "{}: unknown file kind; point clouds are .npy or KITTI .bin, images .npy or .png",
                path.display()
            )),
        }
    }
}

/// An image: float pixels in a tensor whose last two axes are H and W. From a PNG, the
/// shape is `[C, H, W]` (C = 1 or 3) with values in [0, 1] and `png` keeps what the PNG
/// had besides colour.
#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    pub shape: Vec<usize>,
    pub data: Vec<f32>,
    pub png: Option<PngExtras>,
}

/// The parts of a PNG the simulators leave alone: its alpha plane and bit depth.
#[derive(Clone, Debug, PartialEq)]
pub struct PngExtras {
    pub alpha: Option<Vec<f32>>,
    pub sixteen_bit: bool,
}

impl Image {
    /// (planes, height, width) for plane-wise processing; needs at least two axes.
    pub fn planes(&self) -> Result<(usize, usize, usize), String> {
        let n = self.shape.len();
        if n < 2 {
            return Err(format!("an image needs at least two axes (H, W); got shape {:?}", self.shape));
        }
        let (h, w) = (self.shape[n - 2], self.shape[n - 1]);
        if h == 0 || w == 0 {
            return Err(format!("shape {:?} has no pixels", self.shape));
        }
        Ok((self.data.len() / (h * w), h, w))
    }
}

/// The dtype a `.npy` header declares (`'<f4'`, `'<i8'`, ...), for error messages.
fn npy_descr(bytes: &[u8]) -> Option<String> {
    let header = String::from_utf8_lossy(&bytes[..bytes.len().min(512)]).into_owned();
    let start = header.find("'descr':")? + "'descr':".len();
    let rest = header[start..].trim_start().strip_prefix('\'')?;
    Some(rest[..rest.find('\'')?].to_string())
}

/// Reads a float32 (or float64, converted) `.npy` array: shape and row-major values.
pub fn read_npy(path: &Path) -> Result<(Vec<usize>, Vec<f32>), String> {
    let shown = path.display();
    let bytes = std::fs::read(path).map_err(|e| format!("cannot read {shown}: {e}"))?;
    if !bytes.starts_with(b"\x93NUMPY") {
        return Err(format!("{shown}: not a .npy file (no NumPy magic)"));
    }
    if let Ok(a) = ArrayD::<f32>::read_npy(bytes.as_slice()) {
        return Ok((a.shape().to_vec(), a.iter().copied().collect()));
    }
    match ArrayD::<f64>::read_npy(bytes.as_slice()) {
        Ok(a) => Ok((a.shape().to_vec(), a.iter().map(|&v| v as f32).collect())),
        Err(e) => match npy_descr(&bytes).filter(|d| !d.ends_with("f4") && !d.ends_with("f8")) {
            Some(descr) => Err(format!("{shown}: dtype '{descr}'; expected float32 ('<f4') or float64")),
            None => Err(format!("{shown}: cannot read the .npy array ({e}); truncated?")),
        },
    }
}

/// Writes a float32 `.npy` array.
pub fn write_npy(path: &Path, shape: &[usize], data: &[f32]) -> Result<(), String> {
    let shown = path.display();
    let a = ArrayD::from_shape_vec(IxDyn(shape), data.to_vec()).map_err(|e| format!("{shown}: {e}"))?;
    let file = std::fs::File::create(path).map_err(|e| format!("cannot write {shown}: {e}"))?;
    a.write_npy(std::io::BufWriter::new(file)).map_err(|e| format!("cannot write {shown}: {e}"))
}

/// Reads a point cloud: `.npy` `[N, C]` or `.bin` records of `bin_columns` float32s.
pub fn read_cloud(path: &Path, bin_columns: usize) -> Result<PointCloud, String> {
    let shown = path.display();
    let cloud = match Format::of(path)? {
        Format::Npy => {
            let (shape, data) = read_npy(path)?;
            match shape[..] {
                [_, c] if (MIN_COLUMNS..=MAX_COLUMNS).contains(&c) => PointCloud::new(c, data),
                _ => {
                    return Err(format!(
                        "{shown}: shape {shape:?} is not a point cloud [N, 4] (x, y, z, intensity; up to {MAX_COLUMNS} columns)"
                    ));
                }
            }
        }
        Format::Bin => {
            if !(MIN_COLUMNS..=MAX_COLUMNS).contains(&bin_columns) {
                return Err(format!("{bin_columns} columns: a point has {MIN_COLUMNS} to {MAX_COLUMNS} values"));
            }
            let bytes = std::fs::read(path).map_err(|e| format!("cannot read {shown}: {e}"))?;
            let record = 4 * bin_columns;
            if !bytes.len().is_multiple_of(record) {
                return Err(format!(
                    "{shown}: {} bytes is not a whole number of {record}-byte points ({bin_columns} x float32); \
                     truncated, or not a point cloud of {bin_columns} columns (nuScenes .pcd.bin files have 5: --columns 5)",
                    bytes.len()
                ));
            }
            let data = bytes.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect();
            PointCloud::new(bin_columns, data)
        }
        Format::Png => {
            return Err(format!("{shown} is an image; fog and snow apply to lidar point clouds (.bin, .npy [N, 4])"));
        }
    };
    cloud.map_err(|e| format!("{shown}: {e}"))
}

/// Writes a point cloud in the format of the path's extension.
pub fn write_cloud(path: &Path, cloud: &PointCloud) -> Result<(), String> {
    let shown = path.display();
    match Format::of(path)? {
        Format::Npy => write_npy(path, &[cloud.len(), cloud.columns()], cloud.data()),
        Format::Bin => {
            let bytes: Vec<u8> = cloud.data().iter().flat_map(|v| v.to_le_bytes()).collect();
            std::fs::write(path, bytes).map_err(|e| format!("cannot write {shown}: {e}"))
        }
        Format::Png => Err(format!("{shown}: a point cloud is written to .bin or .npy, not .png")),
    }
}

/// Reads an image from `.npy` (any float tensor with H and W last) or `.png`.
pub fn read_image(path: &Path) -> Result<Image, String> {
    let shown = path.display();
    match Format::of(path)? {
        Format::Npy => {
            let (shape, data) = read_npy(path)?;
            let image = Image { shape, data, png: None };
            image.planes().map_err(|e| format!("{shown}: {e}"))?;
            let n = image.shape.len();
            if n >= 3 && image.shape[n - 1] <= 4 && image.shape[n - 3] > 4 {
                return Err(format!(
                    "{shown}: shape {:?} looks channels-last (H, W, C); images are channels-first with H, W last \
                     ([C, H, W], [N, C, H, W]): transpose it",
                    image.shape
                ));
            }
            Ok(image)
        }
        Format::Png => {
            let file = std::fs::File::open(path).map_err(|e| format!("cannot read {shown}: {e}"))?;
            let decoded = ImageReader::with_format(BufReader::new(file), ImageFormat::Png)
                .decode()
                .map_err(|e| format!("{shown}: not a readable PNG ({e})"))?;
            from_dynamic(decoded).map_err(|e| format!("{shown}: {e}"))
        }
        Format::Bin => Err(format!("{shown} is a point cloud; gamma and blur apply to images (.png, .npy)")),
    }
}

/// Interleaved samples → colour planes [C, H, W] in [0, 1], plus the alpha plane.
fn split<T: Copy>(samples: &[T], channels: usize, alpha: bool, h: usize, w: usize, unit: impl Fn(T) -> f32) -> Image {
    let colours = if alpha { channels - 1 } else { channels };
    let mut data = vec![0.0; colours * h * w];
    let mut alpha_plane = alpha.then(|| vec![0.0; h * w]);
    for (i, px) in samples.chunks_exact(channels).enumerate() {
        for c in 0..colours {
            data[c * h * w + i] = unit(px[c]);
        }
        if let Some(a) = alpha_plane.as_mut() {
            a[i] = unit(px[colours]);
        }
    }
    Image { shape: vec![colours, h, w], data, png: Some(PngExtras { alpha: alpha_plane, sixteen_bit: false }) }
}

fn from_dynamic(img: DynamicImage) -> Result<Image, String> {
    let (w, h) = (img.width() as usize, img.height() as usize);
    let u8s = |v: u8| f32::from(v) / 255.0;
    let u16s = |v: u16| f32::from(v) / 65535.0;
    let sixteen = |mut i: Image| {
        if let Some(p) = i.png.as_mut() {
            p.sixteen_bit = true;
        }
        i
    };
    Ok(match img {
        DynamicImage::ImageLuma8(b) => split(b.as_raw(), 1, false, h, w, u8s),
        DynamicImage::ImageLumaA8(b) => split(b.as_raw(), 2, true, h, w, u8s),
        DynamicImage::ImageRgb8(b) => split(b.as_raw(), 3, false, h, w, u8s),
        DynamicImage::ImageRgba8(b) => split(b.as_raw(), 4, true, h, w, u8s),
        DynamicImage::ImageLuma16(b) => sixteen(split(b.as_raw(), 1, false, h, w, u16s)),
        DynamicImage::ImageLumaA16(b) => sixteen(split(b.as_raw(), 2, true, h, w, u16s)),
        DynamicImage::ImageRgb16(b) => sixteen(split(b.as_raw(), 3, false, h, w, u16s)),
        DynamicImage::ImageRgba16(b) => sixteen(split(b.as_raw(), 4, true, h, w, u16s)),
        other => return Err(format!("unsupported PNG pixel format {:?}", other.color())),
    })
}

/// Writes an image: `.npy` float32 in its shape (a PNG's alpha is not written), or
/// `.png` for `[H, W]`, `[1, H, W]` or `[3, H, W]` (leading 1s dropped) with values in
/// [0, 1], rounded to 8 bits (16 if the source PNG had 16), the source PNG's alpha kept.
pub fn write_image(path: &Path, image: &Image) -> Result<(), String> {
    let shown = path.display();
    match Format::of(path)? {
        Format::Npy => write_npy(path, &image.shape, &image.data),
        Format::Png => {
            let mut dims = &image.shape[..];
            while dims.len() > 2 && dims[0] == 1 {
                dims = &dims[1..];
            }
            let (c, h, w) = match *dims {
                [h, w] => (1, h, w),
                [3, h, w] => (3, h, w),
                _ => {
                    return Err(format!(
                        "{shown}: shape {:?} cannot be a PNG (needs [H, W], [1, H, W] or [3, H, W]); write .npy",
                        image.shape
                    ));
                }
            };
            if let Some(i) = image.data.iter().position(|v| !(0.0..=1.0).contains(v)) {
                return Err(format!("{shown}: element {i} is {}; a PNG holds values in [0, 1]", image.data[i]));
            }
            let extras = image.png.as_ref();
            let alpha = extras.and_then(|p| p.alpha.as_ref()).filter(|a| a.len() == h * w);
            let channels = c + usize::from(alpha.is_some());
            let mut samples = Vec::with_capacity(channels * h * w);
            for i in 0..h * w {
                samples.extend((0..c).map(|k| image.data[k * h * w + i]));
                if let Some(a) = alpha {
                    samples.push(a[i]);
                }
            }
            let (wu, hu) = (
                u32::try_from(w).map_err(|_| format!("{shown}: too wide for PNG"))?,
                u32::try_from(h).map_err(|_| format!("{shown}: too tall for PNG"))?,
            );
            let bad = || format!("{shown}: internal error building the PNG buffer");
            let dynamic = if extras.is_some_and(|p| p.sixteen_bit) {
                let s: Vec<u16> = samples.iter().map(|v| (v * 65535.0).round() as u16).collect();
                match channels {
                    1 => DynamicImage::ImageLuma16(ImageBuffer::from_raw(wu, hu, s).ok_or_else(bad)?),
                    2 => DynamicImage::ImageLumaA16(ImageBuffer::from_raw(wu, hu, s).ok_or_else(bad)?),
                    3 => DynamicImage::ImageRgb16(ImageBuffer::from_raw(wu, hu, s).ok_or_else(bad)?),
                    _ => DynamicImage::ImageRgba16(ImageBuffer::from_raw(wu, hu, s).ok_or_else(bad)?),
                }
            } else {
                let s: Vec<u8> = samples.iter().map(|v| (v * 255.0).round() as u8).collect();
                match channels {
                    1 => DynamicImage::ImageLuma8(ImageBuffer::from_raw(wu, hu, s).ok_or_else(bad)?),
                    2 => DynamicImage::ImageLumaA8(ImageBuffer::from_raw(wu, hu, s).ok_or_else(bad)?),
                    3 => DynamicImage::ImageRgb8(ImageBuffer::from_raw(wu, hu, s).ok_or_else(bad)?),
                    _ => DynamicImage::ImageRgba8(ImageBuffer::from_raw(wu, hu, s).ok_or_else(bad)?),
                }
            };
            dynamic.save_with_format(path, ImageFormat::Png).map_err(|e| format!("cannot write {shown}: {e}"))
        }
        Format::Bin => Err(format!("{shown}: an image is written to .png or .npy, not .bin")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn descr_is_found_in_headers() {
        let header = b"\x93NUMPY\x01\x00v\x00{'descr': '<i8', 'fortran_order': False, 'shape': (3,), }";
        assert_eq!(npy_descr(header).as_deref(), Some("<i8"));
        assert_eq!(npy_descr(b"garbage"), None);
    }

    #[test]
    fn formats_by_extension() {
        assert_eq!(Format::of(Path::new("a/000001.BIN")), Ok(Format::Bin));
        assert_eq!(Format::of(Path::new("n.pcd.bin")), Ok(Format::Bin));
        assert!(Format::of(Path::new("x.jpg")).expect_err("jpg").contains("x.jpg: unknown file kind"));
    }
}
