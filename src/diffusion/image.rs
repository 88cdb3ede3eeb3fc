//! Image input for the diffusion model: bytes (PNG, JPEG or WebP) to a square RGB tensor.
//!
//! The header's dimensions are checked against the configured limits before any pixel is
//! decoded, and the decoder itself runs under `image::Limits`, so a small file that claims a
//! huge image is refused cheaply. Then the picture is framed ([`super::framing`]): by default
//! the object is found, centred and scaled as in the image model's training renders, on their
//! white background; transparent pixels are composited on that background.

use std::io::Cursor;

use candle_core::{Device, Tensor};
use image::{DynamicImage, ImageError, ImageReader, Limits};

use super::framing::{Framing, NoObject, frame};

use crate::model::Result;

/// Why an upload is not a usable image.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ImageInputError {
    #[error("not an image in a supported format (PNG, JPEG or WebP)")]
    NotAnImage,
    #[error("the image has zero width or height")]
    ZeroSize,
    #[error("the requested output size is zero")]
    ZeroOutputSize,
    #[error("the image is {width}x{height} pixels, over the limit of {max_width}x{max_height}")]
    TooLarge { width: u32, height: u32, max_width: u32, max_height: u32 },
    #[error("decoding the image needs more memory than the limit of {max_bytes} bytes")]
    TooMuchMemory { max_bytes: u64 },
    #[error("the image data is truncated or corrupt: {0}")]
    Malformed(String),
    #[error("no object found in the picture: {0}; framing centre_crop takes the picture as it is")]
    NoObject(NoObject),
}

/// How an image is turned into encoder input.
#[derive(Debug, Clone, PartialEq)]
pub struct ImageOptions {
    /// Side of the square output in pixels (the image encoder's input size).
    pub size: u32,
    /// RGB colour that transparent pixels are composited on and a found backdrop painted.
    pub background: [u8; 3],
    pub framing: Framing,
    pub max_width: u32,
    pub max_height: u32,
    /// Memory the decoder may allocate, in bytes.
    pub max_alloc: u64,
}

impl ImageOptions {
    /// White background, the object framed, images up to 4096 x 4096, 256 MiB for the
    /// decoder.
    pub fn new(size: u32) -> Self {
        Self {
            size,
            background: [255, 255, 255],
            framing: Framing::Object,
            max_width: 4096,
            max_height: 4096,
            max_alloc: 256 << 20,
        }
    }

    /// Limits for reading the header: memory only, so that an oversized image is reported
    /// with its dimensions (as [`ImageInputError::TooLarge`]) rather than as a decoder error.
    fn header_limits(&self) -> Limits {
        let mut limits = Limits::default();
        limits.max_alloc = Some(self.max_alloc);
        limits
    }

    /// Limits for decoding the pixels.
    fn limits(&self) -> Limits {
        let mut limits = self.header_limits();
        limits.max_image_width = Some(self.max_width);
        limits.max_image_height = Some(self.max_height);
        limits
    }
}

/// A decoded image: `size` x `size` RGB, channel-major (3, size, size), values in [0, 1].
#[derive(Debug, Clone, PartialEq)]
pub struct PreparedImage {
    size: usize,
    pixels: Vec<f32>,
}

impl PreparedImage {
    pub fn size(&self) -> usize {
        self.size
    }

    /// (3, size, size) values in [0, 1].
    pub fn pixels(&self) -> &[f32] {
        &self.pixels
    }
}

fn map_decode_error(e: ImageError, opts: &ImageOptions) -> ImageInputError {
    match e {
        ImageError::Unsupported(_) => ImageInputError::NotAnImage,
        ImageError::Limits(_) => ImageInputError::TooMuchMemory { max_bytes: opts.max_alloc },
        other => ImageInputError::Malformed(other.to_string()),
    }
}

fn reader(bytes: &[u8], limits: Limits) -> Result<ImageReader<Cursor<&[u8]>>, ImageInputError> {
    let mut reader = ImageReader::new(Cursor::new(bytes))
        .with_guessed_format()
        .map_err(|e| ImageInputError::Malformed(e.to_string()))?;
    if reader.format().is_none() {
        return Err(ImageInputError::NotAnImage);
    }
    reader.limits(limits);
    Ok(reader)
}

/// Decodes `bytes` and frames the picture as `opts` say, at `opts.size`. Never panics; every
/// failure is an [`ImageInputError`].
pub fn decode_image(bytes: &[u8], opts: &ImageOptions) -> Result<PreparedImage, ImageInputError> {
    let (width, height) = reader(bytes, opts.header_limits())?
        .into_dimensions()
        .map_err(|e| map_decode_error(e, opts))?;
    if opts.size == 0 {
        return Err(ImageInputError::ZeroOutputSize);
    }
    if width == 0 || height == 0 {
        return Err(ImageInputError::ZeroSize);
    }
    if width > opts.max_width || height > opts.max_height {
        return Err(ImageInputError::TooLarge {
            width,
            height,
            max_width: opts.max_width,
            max_height: opts.max_height,
        });
    }
    let image = reader(bytes, opts.limits())?.decode().map_err(|e| map_decode_error(e, opts))?;
    prepare(&image, opts)
}

/// Framing and the channel-major floats: the part after decoding.
fn prepare(image: &DynamicImage, opts: &ImageOptions) -> Result<PreparedImage, ImageInputError> {
    let framed = frame(&image.to_rgba8(), opts.size, opts.background, opts.framing)
        .map_err(ImageInputError::NoObject)?;
    let size = opts.size as usize;
    let mut pixels = vec![0f32; 3 * size * size];
    for (x, y, p) in framed.enumerate_pixels() {
        for c in 0..3 {
            pixels[(c * size + y as usize) * size + x as usize] = f32::from(p.0[c]) / 255.0;
        }
    }
    Ok(PreparedImage { size, pixels })
}

/// Stacks images of one size into a (B, 3, size, size) tensor.
pub fn images_to_tensor(images: &[PreparedImage], device: &Device) -> Result<Tensor> {
    let size = images.first().map_or(0, |i| i.size);
    if images.is_empty() || images.iter().any(|i| i.size != size) {
        return Err(crate::model::ModelError::bad_input(
            "images_to_tensor needs at least one image, all of one size",
        ));
    }
    let flat: Vec<f32> = images.iter().flat_map(|i| i.pixels.iter().copied()).collect();
    Ok(Tensor::from_vec(flat, (images.len(), 3, size, size), device)?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use image::{ImageFormat, Rgb, RgbImage, Rgba, RgbaImage};
    use proptest::prelude::*;

    fn encode(image: &DynamicImage, format: ImageFormat) -> Vec<u8> {
        let mut out = Cursor::new(Vec::new());
        image.write_to(&mut out, format).unwrap();
        out.into_inner()
    }

    /// 40 x 24: left half red, right half blue, so the crop and the channel order show.
    fn two_colour() -> RgbImage {
        RgbImage::from_fn(40, 24, |x, _| if x < 20 { Rgb([255, 0, 0]) } else { Rgb([0, 0, 255]) })
    }

    fn pixel(img: &PreparedImage, x: usize, y: usize) -> [f32; 3] {
        let s = img.size;
        std::array::from_fn(|c| img.pixels[(c * s + y) * s + x])
    }

    #[test]
    fn png_jpeg_and_webp_round_trip_with_crop_and_resize() {
        let source = DynamicImage::ImageRgb8(two_colour());
        // WebP encoding in the image crate is lossless; JPEG is lossy (hence the tolerance).
        for (format, tol) in
            [(ImageFormat::Png, 0.01), (ImageFormat::WebP, 0.01), (ImageFormat::Jpeg, 0.12)]
        {
            let bytes = encode(&source, format);
            let opts = ImageOptions { framing: Framing::CentreCrop, ..ImageOptions::new(12) };
            let img = decode_image(&bytes, &opts).unwrap();
            assert_eq!(img.size(), 12);
            assert_eq!(img.pixels().len(), 3 * 12 * 12);
            // The centred 24 x 24 square spans x = 8..32, half red and half blue.
            for (x, expect) in [(1, [1.0, 0.0, 0.0]), (10, [0.0, 0.0, 1.0])] {
                let p = pixel(&img, x, 6);
                for c in 0..3 {
                    assert!((p[c] - expect[c]).abs() < tol, "{format:?} x={x}: {p:?}");
                }
            }
        }
    }

    #[test]
    fn alpha_is_composited_on_the_background() {
        let rgba = RgbaImage::from_fn(8, 8, |x, _| {
            if x < 4 { Rgba([0, 0, 0, 0]) } else { Rgba([255, 0, 0, 128]) }
        });
        let bytes = encode(&DynamicImage::ImageRgba8(rgba), ImageFormat::Png);
        let opts = ImageOptions {
            background: [0, 255, 0],
            framing: Framing::CentreCrop,
            ..ImageOptions::new(8)
        };
        let img = decode_image(&bytes, &opts).unwrap();
        assert_eq!(pixel(&img, 0, 0), [0.0, 1.0, 0.0]);
        let p = pixel(&img, 7, 0);
        let half = 128.0 / 255.0;
        assert!((p[0] - half).abs() < 0.01 && (p[1] - (1.0 - half)).abs() < 0.01, "{p:?}");
    }

    #[test]
    fn error_cases() {
        let opts = ImageOptions::new(16);
        assert_eq!(decode_image(b"hello, not an image", &opts), Err(ImageInputError::NotAnImage));
        assert_eq!(decode_image(&[], &opts), Err(ImageInputError::NotAnImage));

        let png = encode(&DynamicImage::ImageRgb8(two_colour()), ImageFormat::Png);
        let mut small = opts.clone();
        (small.max_width, small.max_height) = (32, 32);
        assert_eq!(
            decode_image(&png, &small),
            Err(ImageInputError::TooLarge { width: 40, height: 24, max_width: 32, max_height: 32 })
        );

        let truncated = &png[..png.len() - 20];
        assert!(matches!(decode_image(truncated, &opts), Err(ImageInputError::Malformed(_))));
        // Only the signature and part of the header survive.
        assert!(matches!(decode_image(&png[..20], &opts), Err(ImageInputError::Malformed(_))));

        let mut tight = opts.clone();
        tight.max_alloc = 100;
        assert_eq!(
            decode_image(&png, &tight),
            Err(ImageInputError::TooMuchMemory { max_bytes: 100 })
        );

        assert_eq!(decode_image(&png, &ImageOptions::new(0)), Err(ImageInputError::ZeroOutputSize));

        // A blank picture is an image, but with nothing in it to frame.
        let white = RgbImage::from_pixel(30, 20, Rgb([255, 255, 255]));
        let blank = decode_image(&encode(&white.into(), ImageFormat::Png), &opts).unwrap_err();
        assert_eq!(blank, ImageInputError::NoObject(NoObject::Blank([255, 255, 255])));
        assert!(blank.to_string().contains("framing centre_crop"), "{blank}");
    }

    /// CRC-32 (ISO-HDLC, as PNG uses), so a patched header stays valid.
    fn crc32(bytes: &[u8]) -> u32 {
        let mut crc = !0u32;
        for &b in bytes {
            crc ^= u32::from(b);
            for _ in 0..8 {
                crc = if crc & 1 == 1 { (crc >> 1) ^ 0xEDB8_8320 } else { crc >> 1 };
            }
        }
        !crc
    }

    /// A valid 1 x 1 PNG whose header claims `width` x `height` (with a correct CRC).
    fn png_claiming(width: u32, height: u32) -> Vec<u8> {
        let mut png = encode(&DynamicImage::ImageRgb8(RgbImage::new(1, 1)), ImageFormat::Png);
        // Signature (8), IHDR length (4), "IHDR" (4), width, height, 5 more bytes, CRC.
        png[16..20].copy_from_slice(&width.to_be_bytes());
        png[20..24].copy_from_slice(&height.to_be_bytes());
        let crc = crc32(&png[12..29]);
        png[29..33].copy_from_slice(&crc.to_be_bytes());
        png
    }

    #[test]
    fn a_header_claiming_a_huge_image_is_refused_before_decoding() {
        assert_eq!(
            png_claiming(1, 1).len(),
            encode(&DynamicImage::ImageRgb8(RgbImage::new(1, 1)), ImageFormat::Png).len()
        );
        let as_given = ImageOptions { framing: Framing::CentreCrop, ..ImageOptions::new(4) };
        assert!(decode_image(&png_claiming(1, 1), &as_given).is_ok());
        assert_eq!(
            decode_image(&png_claiming(100_000, 100_000), &ImageOptions::new(16)),
            Err(ImageInputError::TooLarge {
                width: 100_000,
                height: 100_000,
                max_width: 4096,
                max_height: 4096
            })
        );
        // The PNG decoder itself rejects a zero width as a format error; either way it is an
        // error, not a panic or an empty image.
        assert!(matches!(
            decode_image(&png_claiming(0, 5), &ImageOptions::new(16)),
            Err(ImageInputError::ZeroSize | ImageInputError::Malformed(_))
        ));
    }

    #[test]
    fn images_stack_into_a_batch_tensor() {
        let png = encode(&DynamicImage::ImageRgb8(two_colour()), ImageFormat::Png);
        let img = decode_image(&png, &ImageOptions::new(8)).unwrap();
        let t = images_to_tensor(&[img.clone(), img.clone()], &Device::Cpu).unwrap();
        assert_eq!(t.dims(), &[2, 3, 8, 8]);
        assert!(images_to_tensor(&[], &Device::Cpu).is_err());
        let other = decode_image(&png, &ImageOptions::new(4)).unwrap();
        assert!(images_to_tensor(&[img, other], &Device::Cpu).is_err());
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]

        #[test]
        fn arbitrary_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..512)) {
            let _ = decode_image(&bytes, &ImageOptions::new(8));
        }

        #[test]
        fn truncated_and_corrupted_images_never_panic(
            cut in 0usize..2000,
            flip in proptest::option::of((0usize..2000, any::<u8>())),
            format in prop_oneof![
                Just(ImageFormat::Png), Just(ImageFormat::Jpeg), Just(ImageFormat::WebP)
            ],
        ) {
            let mut bytes = encode(&DynamicImage::ImageRgb8(two_colour()), format);
            if let Some((at, value)) = flip {
                let n = bytes.len();
                bytes[at % n] = value;
            }
            bytes.truncate(cut.min(bytes.len()));
            let _ = decode_image(&bytes, &ImageOptions::new(8));
        }
    }
}
