//! `POST /generate` and `GenerateFromImage` input: an image (a raw PNG/JPEG/WebP body, or the
//! `image` part of a multipart form whose other parts are the options) and the options.

use axum::body::Bytes;
use axum::http::{HeaderMap, StatusCode};
use serde::Deserialize;
use utoipa::{IntoParams, ToSchema};

use crate::diffusion::{Framing, ImageInputError, ImageOptions, decode_image};
use crate::engine::{DecodeOptions, ImagePrompt};
use crate::mesh::Format;

use super::error::ApiError;
use super::input::{
    MeshFormat, decode_options, media_type, output_format, seed_schema, unsupported,
};

/// Options of an image request: query parameters of a raw upload, or fields of a multipart
/// form.
#[derive(Debug, Clone, Default, PartialEq, Deserialize, ToSchema, IntoParams)]
#[serde(deny_unknown_fields)]
#[into_params(parameter_in = Query)]
pub struct GenerateOptions {
    /// Face budget (default and maximum: the server's limit, see `/v1/info`).
    #[param(minimum = 1)]
    pub max_faces: Option<usize>,
    /// Euler steps of the diffusion sampler (default: the server's, see `/v1/info`).
    #[param(minimum = 1)]
    pub steps: Option<usize>,
    /// Classifier-free guidance: 0 ignores the image, 1 is plain conditional sampling
    /// (default: the server's).
    pub guidance: Option<f32>,
    /// Seed of the diffusion noise, and of the decoding when it samples.
    #[param(schema_with = seed_schema)]
    pub seed: Option<u64>,
    /// Sampling temperature (default 0: greedy decoding with the face beam).
    #[param(minimum = 0)]
    pub temperature: Option<f32>,
    #[param(minimum = 1)]
    pub top_k: Option<usize>,
    #[param(exclusive_minimum = 0, maximum = 1)]
    pub top_p: Option<f32>,
    /// Partial faces kept while greedy decoding picks each face's coordinates (default 4,
    /// at most 32); 1 picks coordinate by coordinate.
    #[param(minimum = 1, maximum = 32)]
    pub face_beam: Option<usize>,
    /// glb (default), obj, ply or stl.
    #[param(value_type = Option<MeshFormat>)]
    pub format: Option<String>,
    /// object: the object found, centred and scaled as in the image model's training renders,
    /// its backdrop painted white; centre_crop: the largest centred square, as given
    /// (default: the server's, see `/v1/info`).
    #[param(value_type = Option<Framing>)]
    pub framing: Option<String>,
}

/// How this server prepares images and samples when a request does not say.
#[derive(Debug, Clone, PartialEq)]
pub struct ImageDefaults {
    pub steps: usize,
    pub guidance: f32,
    /// Output size (the image model's input) and the decoding limits.
    pub decode: ImageOptions,
}

/// The image's bytes and the options, read from the body but not yet decoded.
#[derive(Debug, Clone)]
pub struct ImageUpload {
    pub image: Bytes,
    pub options: GenerateOptions,
}

#[derive(Debug, Clone)]
pub struct ParsedImageRequest {
    pub prompt: ImagePrompt,
    pub decode: DecodeOptions,
    pub format: Format,
}

/// Media types of a raw image body; a generic or missing type is sniffed from the bytes.
const RAW_TYPES: [&str; 6] =
    ["image/png", "image/jpeg", "image/webp", "application/octet-stream", "image/*", ""];

/// Reads a `/generate` body by its Content-Type. Options come from the query for a raw
/// image, and from the form for a multipart body (where query options are an error, so that
/// nothing given is silently ignored).
pub async fn read_upload(
    headers: &HeaderMap,
    query: GenerateOptions,
    body: Bytes,
) -> Result<ImageUpload, ApiError> {
    let essence = media_type(headers);
    if RAW_TYPES.contains(&essence.as_str()) {
        return Ok(ImageUpload { image: body, options: query });
    }
    if essence != "multipart/form-data" {
        return Err(unsupported(format!(
            "Content-Type {essence:?}: send image/png, image/jpeg or image/webp, or a \
             multipart/form-data form with an `image` part"
        )));
    }
    if query != GenerateOptions::default() {
        return Err(ApiError::invalid(
            "with a multipart form, give the options as form fields, not query parameters",
        ));
    }
    read_form(headers, body).await
}

async fn read_form(headers: &HeaderMap, body: Bytes) -> Result<ImageUpload, ApiError> {
    let content_type = headers
        .get(axum::http::header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .unwrap_or_default();
    let boundary = multer::parse_boundary(content_type)
        .map_err(|e| ApiError::malformed(format!("the multipart Content-Type: {e}")))?;
    let body = futures_util::stream::once(async move { Ok::<_, std::convert::Infallible>(body) });
    let mut form = multer::Multipart::new(body, boundary);
    let mut image = None;
    let mut fields: Vec<(String, String)> = Vec::new();
    let malformed = |e: multer::Error| ApiError::malformed(format!("the multipart form: {e}"));
    while let Some(field) = form.next_field().await.map_err(malformed)? {
        let name = field.name().unwrap_or_default().to_string();
        let data = field.bytes().await.map_err(malformed)?;
        if name == "image" {
            if image.replace(data).is_some() {
                return Err(ApiError::invalid("the form has more than one `image` part"));
            }
        } else {
            let value = String::from_utf8(data.to_vec())
                .map_err(|_| ApiError::invalid(format!("form field {name:?} is not UTF-8 text")))?;
            fields.push((name, value));
        }
    }
    let image = image.ok_or_else(|| ApiError::invalid("the form has no `image` part"))?;
    // The fields as a query string: the same parser, names and errors as for a raw upload.
    let query = serde_urlencoded::to_string(&fields)
        .map_err(|e| ApiError::invalid(format!("form fields: {e}")))?;
    let options = serde_urlencoded::from_str(&query)
        .map_err(|e| ApiError::invalid(format!("form fields: {e}")))?;
    Ok(ImageUpload { image, options })
}

impl ImageUpload {
    /// Decodes the image and checks the options. CPU work: run it off the async runtime.
    pub fn parse(self, defaults: &ImageDefaults) -> Result<ParsedImageRequest, ApiError> {
        let o = self.options;
        let format = output_format(o.format.as_deref())?;
        let seed = o.seed.unwrap_or(0);
        let decode =
            decode_options(o.max_faces, o.temperature, o.top_k, o.top_p, o.face_beam, seed)?;
        let mut options = defaults.decode.clone();
        if let Some(framing) = o.framing.as_deref() {
            options.framing = framing.parse().map_err(ApiError::invalid)?;
        }
        let image = decode_image(&self.image, &options).map_err(image_error)?;
        let prompt = ImagePrompt {
            image,
            steps: o.steps.unwrap_or(defaults.steps),
            guidance: o.guidance.unwrap_or(defaults.guidance),
            seed,
        };
        Ok(ParsedImageRequest { prompt, decode, format })
    }
}

/// An image that cannot be read is a 400; one that reads but shows no object to make a mesh
/// of is a 422, as a mesh with no faces is.
fn image_error(e: ImageInputError) -> ApiError {
    let (status, code) = match e {
        ImageInputError::TooLarge { .. } | ImageInputError::TooMuchMemory { .. } => {
            (StatusCode::BAD_REQUEST, "image_too_large")
        }
        ImageInputError::NoObject(_) => (StatusCode::UNPROCESSABLE_ENTITY, "no_object"),
        _ => (StatusCode::BAD_REQUEST, "invalid_image"),
    };
    ApiError::new(status, code, e.to_string())
}

#[cfg(test)]
mod tests {
    use super::*;
    use axum::http::HeaderValue;
    use axum::http::header::CONTENT_TYPE;

    fn defaults() -> ImageDefaults {
        ImageDefaults { steps: 7, guidance: 2.0, decode: ImageOptions::new(16) }
    }

    /// A dark square on a green backdrop.
    fn png(width: u32, height: u32) -> Vec<u8> {
        let img = image::RgbImage::from_fn(width, height, |x, y| {
            let inside = |v: u32, side: u32| (side / 4..side - side / 4).contains(&v);
            image::Rgb(if inside(x, width) && inside(y, height) { [20; 3] } else { [10, 200, 30] })
        });
        let mut out = std::io::Cursor::new(Vec::new());
        img.write_to(&mut out, image::ImageFormat::Png).unwrap();
        out.into_inner()
    }

    fn headers(content_type: &'static str) -> HeaderMap {
        let mut h = HeaderMap::new();
        h.insert(CONTENT_TYPE, HeaderValue::from_static(content_type));
        h
    }

    fn read(
        ct: &'static str,
        query: GenerateOptions,
        body: Vec<u8>,
    ) -> Result<ImageUpload, ApiError> {
        let rt = tokio::runtime::Builder::new_current_thread().build().unwrap();
        rt.block_on(read_upload(&headers(ct), query, Bytes::from(body)))
    }

    fn form(parts: &[(&str, &[u8])]) -> Vec<u8> {
        let mut body = Vec::new();
        for (name, data) in parts {
            body.extend_from_slice(b"--XyZ\r\n");
            let disposition = if *name == "image" {
                "Content-Disposition: form-data; name=\"image\"; filename=\"a.png\"\r\nContent-Type: image/png\r\n\r\n".to_string()
            } else {
                format!("Content-Disposition: form-data; name=\"{name}\"\r\n\r\n")
            };
            body.extend_from_slice(disposition.as_bytes());
            body.extend_from_slice(data);
            body.extend_from_slice(b"\r\n");
        }
        body.extend_from_slice(b"--XyZ--\r\n");
        body
    }

    const FORM: &str = "multipart/form-data; boundary=XyZ";

    #[test]
    fn raw_images_take_the_query_options_and_the_server_defaults() {
        let query =
            GenerateOptions { steps: Some(3), format: Some("obj".into()), ..Default::default() };
        let parsed = read("image/png", query, png(40, 30)).unwrap().parse(&defaults()).unwrap();
        assert_eq!(parsed.prompt.steps, 3);
        assert_eq!(parsed.prompt.guidance, 2.0);
        assert_eq!(parsed.prompt.image.size(), 16);
        assert_eq!(parsed.format, Format::Obj);
        let sniffed = read("application/octet-stream", GenerateOptions::default(), png(8, 8));
        assert_eq!(sniffed.unwrap().parse(&defaults()).unwrap().prompt.steps, 7);
    }

    #[test]
    fn multipart_forms_carry_the_image_and_the_options() {
        let image = png(20, 20);
        let body =
            form(&[("steps", b"5"), ("guidance", b"1.5"), ("image", &image), ("seed", b"9")]);
        let parsed =
            read(FORM, GenerateOptions::default(), body).unwrap().parse(&defaults()).unwrap();
        assert_eq!((parsed.prompt.steps, parsed.prompt.guidance, parsed.prompt.seed), (5, 1.5, 9));

        let err = |body: Vec<u8>| read(FORM, GenerateOptions::default(), body).unwrap_err();
        assert!(err(form(&[("steps", b"5")])).message.contains("no `image` part"));
        assert!(
            err(form(&[("image", &image), ("image", &image)])).message.contains("more than one")
        );
        assert_eq!(err(form(&[("image", &image), ("stepz", b"5")])).status, 422);
        assert_eq!(err(form(&[("image", &image), ("steps", b"many")])).status, 422);
        assert_eq!(err(b"--XyZ\r\ngarbage".to_vec()).status, 400);
        let with_query = GenerateOptions { steps: Some(2), ..Default::default() };
        assert_eq!(read(FORM, with_query, form(&[("image", &image)])).unwrap_err().status, 422);
        let no_boundary = read("multipart/form-data", GenerateOptions::default(), Vec::new());
        assert_eq!(no_boundary.unwrap_err().status, 400);
    }

    #[test]
    fn framing_is_the_servers_unless_the_request_says() {
        // A dark square in the corner of a white landscape picture: framing it as an object
        // centres it, the centre crop leaves it out.
        let img = image::RgbImage::from_fn(60, 40, |x, y| {
            image::Rgb(if x < 10 && y < 10 { [20, 20, 20] } else { [255, 255, 255] })
        });
        let mut bytes = std::io::Cursor::new(Vec::new());
        img.write_to(&mut bytes, image::ImageFormat::Png).unwrap();
        let prepare = |framing: Option<&str>, defaults: &ImageDefaults| {
            let query =
                GenerateOptions { framing: framing.map(String::from), ..Default::default() };
            read("image/png", query, bytes.get_ref().clone()).unwrap().parse(defaults)
        };
        let centre =
            |d: &ImageDefaults, f| prepare(f, d).unwrap().prompt.image.pixels()[8 * 16 + 8];
        let crop_server = ImageDefaults {
            decode: ImageOptions { framing: Framing::CentreCrop, ..ImageOptions::new(16) },
            ..defaults()
        };
        assert!(centre(&defaults(), None) < 0.2, "the object, centred");
        assert_eq!(centre(&defaults(), Some("centre_crop")), 1.0);
        assert_eq!(centre(&crop_server, None), 1.0);
        assert!(centre(&crop_server, Some("object")) < 0.2);
        let err = prepare(Some("tight"), &defaults()).unwrap_err();
        assert_eq!(err.status, 422);
        assert!(err.message.contains("\"object\" or \"centre_crop\""), "{}", err.message);
    }

    #[test]
    fn bad_images_are_400_and_blank_ones_422_with_a_reason() {
        let parse = |body: Vec<u8>| {
            read("image/png", GenerateOptions::default(), body).unwrap().parse(&defaults())
        };
        assert_eq!(parse(b"not an image".to_vec()).unwrap_err().code, "invalid_image");
        assert_eq!(parse(Vec::new()).unwrap_err().code, "invalid_image");
        let mut truncated = png(64, 64);
        truncated.truncate(truncated.len() / 2);
        assert_eq!(parse(truncated).unwrap_err().status, 400);
        let tight = ImageDefaults {
            decode: ImageOptions { max_width: 32, max_height: 32, ..ImageOptions::new(16) },
            ..defaults()
        };
        let upload = read("image/png", GenerateOptions::default(), png(64, 8)).unwrap();
        assert_eq!(upload.parse(&tight).unwrap_err().code, "image_too_large");
        let blank = image::RgbImage::from_pixel(40, 30, image::Rgb([250, 250, 250]));
        let mut bytes = std::io::Cursor::new(Vec::new());
        blank.write_to(&mut bytes, image::ImageFormat::Png).unwrap();
        let err = parse(bytes.into_inner()).unwrap_err();
        assert_eq!(err.status, 422);
        assert_eq!(err.code, "no_object", "{}", err.message);
        assert_eq!(
            read("text/plain", GenerateOptions::default(), png(8, 8)).unwrap_err().status,
            400
        );
    }
}
