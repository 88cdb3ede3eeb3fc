//! Optional API keys: `Authorization: Bearer <key>` on HTTP, the same `authorization` metadata
//! on gRPC. One tower layer serves both servers, so that the open paths (health, metrics, the
//! viewer page) are one list and a refusal is counted and answered the same way.
//!
//! Keys are kept only as SHA-256 digests: a request's key is hashed too and compared with
//! every configured digest in constant time, without stopping at a match, so that neither the
//! time taken nor its dependence on length tells a caller how close a guess was. Nothing here
//! logs or displays a key or its digest.

use std::path::Path;
use std::sync::Arc;
use std::task::{Context, Poll};

use axum::http::{HeaderValue, Request, Response, StatusCode, header};
use axum::response::IntoResponse;
use futures_util::future::{Either, Ready, ready};
use sha2::{Digest, Sha256};
use subtle::{Choice, ConstantTimeEq};
use thiserror::Error;
use tower::{Layer, Service};

use super::error::ApiError;
use crate::engine::Metrics;

/// Paths that need no key unless configured otherwise: probes and metrics; the viewer page,
/// its files and the OpenAPI document (static, the same in every deployment: see
/// docs/decisions.md, "Authentication"); gRPC health and reflection.
pub const DEFAULT_OPEN_PATHS: &str = "/healthz,/readyz,/metrics,/,/ui/*,/openapi.json,\
    /grpc.health.v1.Health/*,/grpc.reflection.*";

/// The metric reason of a refused request.
const REASON: &str = "unauthenticated";

#[derive(Debug, Error, PartialEq, Eq)]
pub enum AuthError {
    /// The key's position, never the key.
    #[error(
        "API key {position}: a key must be 1 to 4096 characters among letters, digits and \
         - . _ ~ + / = (the Bearer token syntax)"
    )]
    InvalidKey { position: usize },
    #[error("API key file {path}: {message}")]
    KeyFile { path: String, message: String },
    #[error("open path {0:?}: give a path that starts with /, optionally ending in *")]
    OpenPath(String),
}

/// The configured keys, as digests. Its `Debug` shows how many there are and nothing else.
#[derive(Clone, Default)]
pub struct ApiKeys {
    digests: Vec<[u8; 32]>,
}

impl std::fmt::Debug for ApiKeys {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "ApiKeys({} configured)", self.digests.len())
    }
}

fn digest(key: &[u8]) -> [u8; 32] {
    Sha256::digest(key).into()
}

/// RFC 6750's b64token characters: what fits in a header value and needs no quoting.
fn valid_key(key: &str) -> bool {
    (1..=4096).contains(&key.len())
        && key.bytes().all(|b| b.is_ascii_alphanumeric() || b"-._~+/=".contains(&b))
}

impl ApiKeys {
    /// The keys given (flags, environment) and, when `file` is given, the keys in it. Keys are
    /// trimmed; a duplicate is kept once.
    pub fn new<S: AsRef<str>>(keys: &[S], file: Option<&Path>) -> Result<Self, AuthError> {
        let mut all: Vec<String> = keys.iter().map(|k| k.as_ref().trim().to_string()).collect();
        if let Some(path) = file {
            all.extend(read_key_file(path)?);
        }
        let mut digests = Vec::with_capacity(all.len());
        for (i, key) in all.iter().enumerate() {
            if !valid_key(key) {
                return Err(AuthError::InvalidKey { position: i + 1 });
            }
            let d = digest(key.as_bytes());
            if !digests.contains(&d) {
                digests.push(d);
            }
        }
        Ok(Self { digests })
    }

    /// How many distinct keys there are: with none, every request is let through.
    pub fn len(&self) -> usize {
        self.digests.len()
    }

    pub fn is_empty(&self) -> bool {
        self.digests.is_empty()
    }

    /// Whether an `Authorization` header value carries one of the keys. Every key is compared,
    /// whatever the outcome; a missing or malformed header compares a digest of nothing.
    pub fn accepts(&self, authorization: Option<&HeaderValue>) -> bool {
        let token = authorization.and_then(|v| bearer_token(v.as_bytes())).unwrap_or_default();
        let given = digest(token);
        let mut any = Choice::from(0);
        for key in &self.digests {
            any |= key.ct_eq(&given);
        }
        bool::from(any)
    }
}

/// The token of `Bearer <token>` (the scheme in any case, as RFC 7235 allows).
fn bearer_token(value: &[u8]) -> Option<&[u8]> {
    let (scheme, token) = value.split_at_checked(7)?;
    (scheme.eq_ignore_ascii_case(b"bearer ")).then(|| token.trim_ascii())
}

/// One key per line; blank lines and lines starting with `#` are skipped. A file that cannot
/// be read or holds no key is an error naming it.
pub fn read_key_file(path: &Path) -> Result<Vec<String>, AuthError> {
    let error = |message: String| AuthError::KeyFile { path: path.display().to_string(), message };
    let text = std::fs::read_to_string(path).map_err(|e| error(e.to_string()))?;
    let keys: Vec<String> = text
        .lines()
        .map(str::trim)
        .filter(|l| !l.is_empty() && !l.starts_with('#'))
        .map(str::to_string)
        .collect();
    if keys.is_empty() {
        return Err(error("holds no key (one a line; # starts a comment)".into()));
    }
    Ok(keys)
}

/// A path let through without a key: exact, or a prefix when it ends in `*`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum OpenPath {
    Exact(String),
    Prefix(String),
}

impl std::str::FromStr for OpenPath {
    type Err = AuthError;

    fn from_str(s: &str) -> Result<Self, AuthError> {
        let s = s.trim();
        if !s.starts_with('/') || s[..s.len() - 1].contains('*') {
            return Err(AuthError::OpenPath(s.to_string()));
        }
        Ok(match s.strip_suffix('*') {
            Some(prefix) => Self::Prefix(prefix.to_string()),
            None => Self::Exact(s.to_string()),
        })
    }
}

impl OpenPath {
    fn matches(&self, path: &str) -> bool {
        match self {
            Self::Exact(p) => path == p,
            Self::Prefix(p) => path.starts_with(p.as_str()),
        }
    }
}

/// The keys and the paths that need none.
#[derive(Debug, Clone)]
pub struct AuthConfig {
    pub keys: ApiKeys,
    pub open_paths: Vec<OpenPath>,
}

impl Default for AuthConfig {
    /// No keys: every request is let through.
    fn default() -> Self {
        let open_paths = DEFAULT_OPEN_PATHS.split(',').filter_map(|p| p.parse().ok()).collect();
        Self { keys: ApiKeys::default(), open_paths }
    }
}

impl AuthConfig {
    fn allows<B>(&self, request: &Request<B>) -> bool {
        self.keys.is_empty()
            || self.open_paths.iter().any(|p| p.matches(request.uri().path()))
            || self.keys.accepts(request.headers().get(header::AUTHORIZATION))
    }
}

/// The answer to a request without a valid key; one for each protocol.
pub trait Refusal: Sized {
    fn refusal() -> Self;
}

/// 401 with `WWW-Authenticate: Bearer` and the usual error body; the same whatever was wrong.
impl Refusal for Response<axum::body::Body> {
    fn refusal() -> Self {
        let mut response = ApiError::new(
            StatusCode::UNAUTHORIZED,
            REASON,
            "this server needs an API key: send Authorization: Bearer <key>",
        )
        .into_response();
        response.headers_mut().insert(header::WWW_AUTHENTICATE, HeaderValue::from_static("Bearer"));
        response
    }
}

/// `UNAUTHENTICATED`, the same whatever was wrong.
impl Refusal for Response<tonic::body::Body> {
    fn refusal() -> Self {
        tonic::Status::unauthenticated(
            "unauthenticated: this server needs an API key: send metadata authorization: \
             Bearer <key>",
        )
        .into_http()
    }
}

/// Lets through requests to open paths or with a valid key; refuses the rest, counted as
/// `unauthenticated` among the rejected requests.
#[derive(Clone)]
pub struct AuthLayer {
    config: Arc<AuthConfig>,
    metrics: Arc<Metrics>,
}

impl AuthLayer {
    pub fn new(config: AuthConfig, metrics: Arc<Metrics>) -> Self {
        Self { config: Arc::new(config), metrics }
    }
}

impl<S> Layer<S> for AuthLayer {
    type Service = RequireKey<S>;

    fn layer(&self, inner: S) -> RequireKey<S> {
        RequireKey { inner, layer: self.clone() }
    }
}

#[derive(Clone)]
pub struct RequireKey<S> {
    inner: S,
    layer: AuthLayer,
}

impl<S, B, R> Service<Request<B>> for RequireKey<S>
where
    S: Service<Request<B>, Response = R>,
    R: Refusal,
{
    type Response = R;
    type Error = S::Error;
    type Future = Either<Ready<Result<R, S::Error>>, S::Future>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), S::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, request: Request<B>) -> Self::Future {
        if self.layer.config.allows(&request) {
            return Either::Right(self.inner.call(request));
        }
        self.layer.metrics.reject(REASON);
        tracing::info!(path = request.uri().path(), code = REASON, "refused: no valid API key");
        Either::Left(ready(Ok(R::refusal())))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn keys(list: &[&str]) -> ApiKeys {
        ApiKeys::new(list, None).unwrap()
    }

    fn header(value: &str) -> HeaderValue {
        HeaderValue::from_str(value).unwrap()
    }

    #[test]
    fn a_bearer_header_with_any_configured_key_is_accepted() {
        let k = keys(&["first-key", "second.key"]);
        assert_eq!(k.len(), 2);
        assert!(k.accepts(Some(&header("Bearer first-key"))));
        assert!(k.accepts(Some(&header("Bearer second.key"))));
        assert!(k.accepts(Some(&header("bearer second.key"))));
        assert!(k.accepts(Some(&header("BEARER  first-key "))));
    }

    #[test]
    fn wrong_missing_and_malformed_headers_are_refused() {
        let k = keys(&["first-key"]);
        for bad in [
            "Bearer first-kez",
            "Bearer first-key2",
            "Bearer first",
            "Bearer ",
            "Bearer",
            "first-key",
            "Basic first-key",
            "Bearerfirst-key",
            "",
        ] {
            assert!(!k.accepts(Some(&header(bad))), "{bad:?}");
        }
        assert!(!k.accepts(None));
    }

    #[test]
    fn keys_are_trimmed_deduplicated_and_checked_without_echoing_them() {
        let k = ApiKeys::new(&[" abc ", "abc", "A-z_0.9~+/="], None).unwrap();
        assert_eq!(k.len(), 2);
        assert!(k.accepts(Some(&header("Bearer abc"))));
        for bad in ["", "has space", "quote\"d", "comma,key", "é"] {
            let e = ApiKeys::new(&["good", bad], None).unwrap_err();
            assert_eq!(e, AuthError::InvalidKey { position: 2 });
            if !bad.is_empty() {
                assert!(!e.to_string().contains(bad), "{e}");
            }
        }
        assert!(ApiKeys::new(&["x".repeat(4097)], None).is_err());
    }

    #[test]
    fn debug_output_shows_no_key() {
        let k = keys(&["secret-value-1"]);
        let shown = format!("{:?}", AuthConfig { keys: k, ..AuthConfig::default() });
        assert!(!shown.contains("secret-value-1"), "{shown}");
        assert!(shown.contains("ApiKeys(1 configured)"), "{shown}");
    }

    #[test]
    fn a_key_file_skips_blank_lines_and_comments_and_must_hold_a_key() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("keys");
        std::fs::write(&path, "# team a\nkey-one\n\n  key-two  \n# key-three\n").unwrap();
        assert_eq!(read_key_file(&path).unwrap(), ["key-one", "key-two"]);
        let k = ApiKeys::new(&["flag-key"], Some(&path)).unwrap();
        assert!(k.accepts(Some(&header("Bearer key-two"))));
        assert!(k.accepts(Some(&header("Bearer flag-key"))));
        assert!(!k.accepts(Some(&header("Bearer # key-three"))));

        std::fs::write(&path, "# nothing\n\n").unwrap();
        let e = read_key_file(&path).unwrap_err().to_string();
        assert!(e.contains(&path.display().to_string()) && e.contains("no key"), "{e}");
        let missing = dir.path().join("absent");
        let e = ApiKeys::new::<&str>(&[], Some(&missing)).unwrap_err().to_string();
        assert!(e.contains(&missing.display().to_string()), "{e}");
    }

    #[test]
    fn open_paths_are_exact_or_prefixes() {
        let config = AuthConfig { keys: keys(&["k"]), ..AuthConfig::default() };
        let request = |path: &str| Request::get(path).body(()).unwrap();
        for open in ["/healthz", "/", "/ui/app.js", "/grpc.health.v1.Health/Check"] {
            assert!(config.allows(&request(open)), "{open}");
        }
        for closed in ["/reconstruct", "/v1/info", "/healthz/x", "/uix", "/nowhere"] {
            assert!(!config.allows(&request(closed)), "{closed}");
        }
        let keyed = Request::get("/v1/info").header("authorization", "Bearer k").body(()).unwrap();
        assert!(config.allows(&keyed));
        assert!(AuthConfig::default().allows(&request("/reconstruct")));

        assert_eq!("/a*".parse(), Ok(OpenPath::Prefix("/a".into())));
        for bad in ["healthz", "/a*b", "", "*"] {
            assert!(bad.parse::<OpenPath>().is_err(), "{bad}");
        }
    }
}
