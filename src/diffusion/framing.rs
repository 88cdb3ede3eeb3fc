//! The square of a picture the image model sees.
//!
//! The image model learned from renders with the object centred on a white background and the
//! longer side of its box spanning [`TRAINING_FILL`] of the frame (the training camera frames
//! the normalized cube's bounding sphere, so how much of it an object spans tells its shape).
//! Users send tight product shots, objects off the centre of landscape photos, studio
//! backdrops of other colours: taken as given, pictures the model never saw.
//! [`Framing::Object`] finds the object (by its alpha, or against a uniform backdrop read off
//! the picture's border), paints the backdrop the training background, centres the object's
//! box, and scales it into the training range: a picture framed like the training renders
//! keeps its scale. Where it cannot tell the object from its surroundings (a cluttered photo),
//! it falls back to the largest centred square, which is all [`Framing::CentreCrop`] does. A
//! picture with nothing on its backdrop (one colour throughout, or all transparent) is refused
//! with [`NoObject`]: a mesh made up from a blank picture would be noise.

use std::ops::RangeInclusive;
use std::str::FromStr;

use image::imageops::{self, FilterType};
use image::{GenericImageView, Rgb, RgbImage, Rgba, RgbaImage};
use utoipa::ToSchema;

/// How a picture is framed for the image model (request option `framing`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, ToSchema)]
#[schema(rename_all = "snake_case")]
pub enum Framing {
    /// Find the object, paint the backdrop white, centre and scale the object as in training.
    #[default]
    Object,
    /// The largest centred square, as given: for pictures framed like the training renders.
    CentreCrop,
}

impl Framing {
    pub fn name(self) -> &'static str {
        match self {
            Framing::Object => "object",
            Framing::CentreCrop => "centre_crop",
        }
    }
}

impl FromStr for Framing {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        [Framing::Object, Framing::CentreCrop]
            .into_iter()
            .find(|f| f.name() == s)
            .ok_or_else(|| format!("framing must be \"object\" or \"centre_crop\", got {s:?}"))
    }
}

impl std::fmt::Display for Framing {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Share of the frame the longer side of the object's box spans in the image model's training
/// renders: the middle half of their shares (median 0.58, 5th to 95th percentile 0.43-0.74)
/// over 150 training meshes seen from the training views' camera (docs/decisions.md, "Pictures
/// are framed like the training renders"); a test checks it against `ViewConfig`.
pub const TRAINING_FILL: RangeInclusive<f32> = 0.53..=0.62;

/// A pixel whose channels are all within this of the backdrop's (of 255) is backdrop. JPEG
/// noise on a flat backdrop stays well under it; the object's own shading is farther away.
const BACKDROP_TOLERANCE: u8 = 24;

/// Share of the border's pixels that must match its median colour for the border to be read
/// as a backdrop: an object may touch the border, a cluttered scene's border does not match.
const UNIFORM_BORDER_SHARE: f32 = 0.9;

/// Why [`Framing::Object`] found nothing to frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum NoObject {
    #[error("no pixel of the picture is at least half opaque")]
    Transparent,
    #[error("the picture is one colour throughout (RGB {0:?}, give or take {BACKDROP_TOLERANCE})")]
    Blank([u8; 3]),
}

/// `image` framed as `framing` says, alpha composited on `background`, resized to `size` x
/// `size`.
pub fn frame(
    image: &RgbaImage,
    size: u32,
    background: [u8; 3],
    framing: Framing,
) -> Result<RgbImage, NoObject> {
    let object = match framing {
        Framing::Object => find_object(image)?,
        Framing::CentreCrop => None,
    };
    Ok(match object {
        Some(object) => centre_object(image, &object, size, background),
        None => centre_crop(image, size, background),
    })
}

/// Where the object is: its box in pixels and, when the picture is opaque, the backdrop it
/// stands on.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Object {
    left: u32,
    top: u32,
    width: u32,
    height: u32,
    backdrop: Option<[u8; 3]>,
}

/// The object of a picture with transparency is its pixels at least half opaque; of an opaque
/// one, its pixels off the backdrop. `None` when neither tells (no uniform backdrop).
fn find_object(image: &RgbaImage) -> Result<Option<Object>, NoObject> {
    let transparent = image.pixels().any(|p| p[3] < u8::MAX);
    let backdrop = if transparent {
        None
    } else {
        // Without a uniform backdrop (a cluttered photo) the object cannot be told.
        let Some(colour) = uniform_border(image) else { return Ok(None) };
        Some(colour)
    };
    let is_object = |p: &Rgba<u8>| match backdrop {
        None => p[3] >= 128,
        Some(colour) => !near(p, colour),
    };
    let (mut x0, mut y0, mut x1, mut y1) = (u32::MAX, u32::MAX, 0, 0);
    for (x, y, p) in image.enumerate_pixels() {
        if is_object(p) {
            (x0, y0, x1, y1) = (x0.min(x), y0.min(y), x1.max(x), y1.max(y));
        }
    }
    if x0 > x1 {
        // No object pixel: the box's corners are still crossed.
        return Err(backdrop.map_or(NoObject::Transparent, NoObject::Blank));
    }
    Ok(Some(Object { left: x0, top: y0, width: x1 - x0 + 1, height: y1 - y0 + 1, backdrop }))
}

fn near(p: &Rgba<u8>, colour: [u8; 3]) -> bool {
    (0..3).all(|c| p[c].abs_diff(colour[c]) <= BACKDROP_TOLERANCE)
}

/// The border's median colour, if enough of the border is of it.
fn uniform_border(image: &RgbaImage) -> Option<[u8; 3]> {
    let (w, h) = image.dimensions();
    let mut border: Vec<Rgba<u8>> = (0..w)
        .flat_map(|x| [(x, 0), (x, h - 1)])
        .chain((0..h).flat_map(|y| [(0, y), (w - 1, y)]))
        .map(|(x, y)| *image.get_pixel(x, y))
        .collect();
    let median = |border: &mut Vec<Rgba<u8>>, c: usize| {
        let mid = border.len() / 2;
        border.select_nth_unstable_by_key(mid, |p| p[c]).1[c]
    };
    let colour = [median(&mut border, 0), median(&mut border, 1), median(&mut border, 2)];
    let matching = border.iter().filter(|p| near(p, colour)).count();
    (matching as f32 >= UNIFORM_BORDER_SHARE * border.len() as f32).then_some(colour)
}

/// The object's box at the frame's centre, on `background` (the backdrop inside the box
/// becomes `background` too), spanning as much of the frame as of the picture's largest
/// centred square, brought into [`TRAINING_FILL`].
fn centre_object(image: &RgbaImage, object: &Object, size: u32, background: [u8; 3]) -> RgbImage {
    let crop = image.view(object.left, object.top, object.width, object.height).to_image();
    let flat = RgbImage::from_fn(crop.width(), crop.height(), |x, y| {
        let p = crop.get_pixel(x, y);
        match object.backdrop {
            Some(colour) if near(p, colour) => Rgb(background),
            _ => composite(p, background),
        }
    });
    let longer = object.width.max(object.height) as f32;
    let as_given = longer / image.width().min(image.height()) as f32;
    let fill = as_given.clamp(*TRAINING_FILL.start(), *TRAINING_FILL.end());
    let scale = size as f32 * fill / longer;
    let scaled = |side: u32| ((side as f32 * scale).round() as u32).clamp(1, size);
    let (width, height) = (scaled(object.width), scaled(object.height));
    let resized = imageops::resize(&flat, width, height, FilterType::Triangle);
    let mut framed = RgbImage::from_pixel(size, size, Rgb(background));
    imageops::replace(
        &mut framed,
        &resized,
        i64::from((size - width) / 2),
        i64::from((size - height) / 2),
    );
    framed
}

/// The largest centred square, composited on `background` and resized.
fn centre_crop(image: &RgbaImage, size: u32, background: [u8; 3]) -> RgbImage {
    let side = image.width().min(image.height());
    let square = image.view((image.width() - side) / 2, (image.height() - side) / 2, side, side);
    let composited =
        RgbImage::from_fn(side, side, |x, y| composite(&square.get_pixel(x, y), background));
    imageops::resize(&composited, size, size, FilterType::Triangle)
}

fn composite(p: &Rgba<u8>, background: [u8; 3]) -> Rgb<u8> {
    let alpha = f32::from(p[3]) / 255.0;
    Rgb(std::array::from_fn(|c| {
        let blended = f32::from(p[c]) * alpha + f32::from(background[c]) * (1.0 - alpha);
        blended.round().clamp(0.0, 255.0) as u8
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    const GREY: [u8; 3] = [222, 224, 230];
    const WHITE: [u8; 3] = [255, 255, 255];

    /// A `w` x `h` opaque picture on `backdrop` with a shaded `ow` x `oh` box at (`ox`, `oy`):
    /// dark on its left half, mid-grey on its right, so that scale and position show.
    fn picture(
        w: u32,
        h: u32,
        backdrop: [u8; 3],
        (ox, oy, ow, oh): (u32, u32, u32, u32),
    ) -> RgbaImage {
        RgbaImage::from_fn(w, h, |x, y| {
            let inside = (ox..ox + ow).contains(&x) && (oy..oy + oh).contains(&y);
            match (inside, x < ox + ow / 2) {
                (false, _) => Rgba([backdrop[0], backdrop[1], backdrop[2], 255]),
                (true, true) => Rgba([40, 40, 40, 255]),
                (true, false) => Rgba([120, 120, 120, 255]),
            }
        })
    }

    /// The box of the pixels that are not `background`: (left, top, width, height).
    fn object_box(image: &RgbImage, background: [u8; 3]) -> (u32, u32, u32, u32) {
        let inside: Vec<(u32, u32)> = image
            .enumerate_pixels()
            .filter(|(_, _, p)| p.0 != background)
            .map(|(x, y, _)| (x, y))
            .collect();
        let (x0, x1) =
            (inside.iter().map(|p| p.0).min().unwrap(), inside.iter().map(|p| p.0).max().unwrap());
        let (y0, y1) =
            (inside.iter().map(|p| p.1).min().unwrap(), inside.iter().map(|p| p.1).max().unwrap());
        (x0, y0, x1 - x0 + 1, y1 - y0 + 1)
    }

    #[test]
    fn an_object_anywhere_on_a_backdrop_is_centred_and_scaled_into_the_training_range() {
        let size = 64;
        let side = |fill: f32| (size as f32 * fill).round() as u32;
        let (least, most) = (side(*TRAINING_FILL.start()), side(*TRAINING_FILL.end()));
        // A small box near a landscape picture's corner comes out at the least fill; a large
        // one filling a portrait's width and a box twice as wide as tall filling a square at
        // the most; one as large as training renders have keeps its share. All centred, on
        // white.
        for (w, h, object, (width, height)) in [
            (640, 480, (500, 40, 100, 100), (least, least)),
            (300, 500, (10, 100, 280, 280), (most, most)),
            (200, 200, (10, 80, 180, 90), (most, most / 2)),
            (100, 100, (5, 5, 60, 60), (side(0.6), side(0.6))),
        ] {
            let framed = frame(&picture(w, h, GREY, object), size, WHITE, Framing::Object).unwrap();
            let (left, top, got_width, got_height) = object_box(&framed, WHITE);
            assert!(got_width.abs_diff(width) <= 1 && got_height.abs_diff(height) <= 1);
            assert!(left.abs_diff((size - got_width) / 2) <= 1);
            assert!(top.abs_diff((size - got_height) / 2) <= 1);
            assert_eq!(framed.get_pixel(0, 0).0, WHITE, "the backdrop is painted white");
            // The object's own shades survive: dark on the left, mid-grey on the right.
            let mid = size / 2;
            assert!(framed.get_pixel(left + 2, mid)[0] < 60);
            assert!((100..140).contains(&framed.get_pixel(left + got_width - 3, mid)[0]));
        }
    }

    #[test]
    fn transparency_tells_the_object_whatever_the_colours_behind_it() {
        // Transparent pixels of any colour around a half-opaque box and an opaque core.
        let image = RgbaImage::from_fn(100, 60, |x, y| {
            if (70..90).contains(&x) && (10..30).contains(&y) {
                Rgba([200, 0, 0, 255])
            } else if (68..92).contains(&x) && (8..32).contains(&y) {
                Rgba([200, 0, 0, 40]) // a soft edge under half opacity: not the object's box
            } else {
                Rgba([(x * 2) as u8, (y * 4) as u8, 7, 0])
            }
        });
        let framed = frame(&image, 40, WHITE, Framing::Object).unwrap();
        let (left, top, width, height) = object_box(&framed, WHITE);
        // 20 of the picture's 60 rows: brought up to the least training fill.
        let side = (40.0 * TRAINING_FILL.start()).round() as u32;
        assert!(width.abs_diff(side) <= 1 && height.abs_diff(side) <= 1, "{width} x {height}");
        assert!(left.abs_diff((40 - width) / 2) <= 1 && top.abs_diff((40 - height) / 2) <= 1);
        assert_eq!(framed.get_pixel(20, 20).0, [200, 0, 0]);
    }

    #[test]
    fn without_a_uniform_backdrop_the_centre_square_is_taken() {
        // A border of many colours (a cluttered photo): the object cannot be told from its
        // surroundings, so the framing is the centre crop's.
        let cluttered =
            RgbaImage::from_fn(90, 60, |x, y| Rgba([(x * 3) as u8, (y * 4) as u8, 90, 255]));
        assert_eq!(
            frame(&cluttered, 16, WHITE, Framing::Object),
            frame(&cluttered, 16, WHITE, Framing::CentreCrop)
        );
        let crop = frame(&picture(90, 60, GREY, (0, 0, 0, 0)), 8, WHITE, Framing::CentreCrop);
        assert_eq!(crop.unwrap().get_pixel(3, 3).0, GREY, "the centre crop keeps the backdrop");
    }

    #[test]
    fn a_picture_with_nothing_on_its_backdrop_has_no_object() {
        // An empty backdrop (JPEG-like noise within the tolerance included), a fully
        // transparent picture, one whose pixels are all under half opaque: refused as an
        // object, taken as they are by the centre crop.
        let empty = picture(80, 50, GREY, (0, 0, 0, 0));
        let noisy = RgbaImage::from_fn(80, 50, |x, y| {
            let jitter = ((x * 7 + y * 13) % 21) as u8;
            Rgba([GREY[0] - jitter, GREY[1] - jitter, GREY[2] - jitter, 255])
        });
        let transparent = RgbaImage::from_pixel(30, 50, Rgba([10, 20, 30, 0]));
        let faint = RgbaImage::from_pixel(30, 50, Rgba([10, 20, 30, 127]));
        for (image, expected) in [
            (&empty, NoObject::Blank(GREY)),
            (&transparent, NoObject::Transparent),
            (&faint, NoObject::Transparent),
        ] {
            assert_eq!(frame(image, 16, WHITE, Framing::Object), Err(expected));
            assert!(frame(image, 16, WHITE, Framing::CentreCrop).is_ok());
        }
        assert!(matches!(frame(&noisy, 16, WHITE, Framing::Object), Err(NoObject::Blank(_))));
        let message = NoObject::Blank(GREY).to_string();
        assert!(message.contains("one colour") && message.contains("222, 224, 230"), "{message}");
    }

    #[test]
    fn one_pixel_pictures_and_objects_are_framed_without_panicking() {
        for (w, h) in [(1, 1), (1, 7), (7, 1)] {
            // One colour: nothing to find, but no panic either way.
            let image = RgbaImage::from_pixel(w, h, Rgba([9, 9, 9, 255]));
            assert_eq!(frame(&image, 5, WHITE, Framing::Object), Err(NoObject::Blank([9, 9, 9])));
            let crop = frame(&image, 5, WHITE, Framing::CentreCrop).unwrap();
            assert_eq!(crop.dimensions(), (5, 5));
        }
        let dot = picture(50, 50, GREY, (25, 25, 1, 1));
        let framed = frame(&dot, 9, WHITE, Framing::Object).unwrap();
        assert_eq!(framed.dimensions(), (9, 9));
        assert_ne!(framed.get_pixel(4, 4).0, WHITE, "one pixel is an object, scaled up");
    }

    #[test]
    fn framing_names_parse_and_others_are_refused() {
        for f in [Framing::Object, Framing::CentreCrop] {
            assert_eq!(f.name().parse::<Framing>(), Ok(f));
        }
        let err = "centre".parse::<Framing>().unwrap_err();
        assert!(err.contains("\"object\" or \"centre_crop\""), "{err}");
    }
}
