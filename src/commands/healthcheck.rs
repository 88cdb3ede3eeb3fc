//! `meshstream healthcheck`: asks a running server whether it is ready, for a container's
//! HEALTHCHECK, so that the image needs no curl. A plain HTTP/1.0 GET over std's TCP stream
//! suffices for the server's own loopback address: exit status 0 on a 2xx answer, else 1.

use std::io::{Read, Write};
use std::net::{TcpStream, ToSocketAddrs};
use std::time::Duration;

use anyhow::{Context, bail};
use clap::Args;

#[derive(Args)]
pub struct HealthcheckArgs {
    /// The address to ask (http:// only: the server's own port, from inside its container).
    #[arg(
        long,
        env = "MESHSTREAM_HEALTHCHECK_URL",
        default_value = "http://127.0.0.1:8080/readyz"
    )]
    url: String,
    /// Seconds to wait for the whole answer.
    #[arg(long, default_value_t = 3.0)]
    timeout: f64,
}

pub fn run(args: &HealthcheckArgs) -> anyhow::Result<()> {
    let timeout = Duration::try_from_secs_f64(args.timeout)
        .ok()
        .filter(|t| !t.is_zero())
        .with_context(|| format!("--timeout {}: a positive number of seconds", args.timeout))?;
    let status = get_status(&args.url, timeout).with_context(|| format!("GET {}", args.url))?;
    if !(200..300).contains(&status) {
        bail!("GET {}: HTTP status {status}", args.url);
    }
    Ok(())
}

/// The status code of a GET of `url`.
fn get_status(url: &str, timeout: Duration) -> anyhow::Result<u16> {
    let (authority, path) = split_url(url)?;
    let addr = authority
        .to_socket_addrs()
        .with_context(|| format!("resolving {authority}"))?
        .next()
        .with_context(|| format!("{authority} resolves to no address"))?;
    let mut stream = TcpStream::connect_timeout(&addr, timeout)?;
    stream.set_read_timeout(Some(timeout))?;
    stream.set_write_timeout(Some(timeout))?;
    write!(stream, "GET {path} HTTP/1.0\r\nHost: {authority}\r\nConnection: close\r\n\r\n")?;
    // The status line is all that is needed; a ready answer is a few bytes, a longer one is cut.
    let mut head = Vec::new();
    stream.take(4096).read_to_end(&mut head)?;
    parse_status(&head)
}

/// `http://HOST:PORT/PATH` into `HOST:PORT` (port 80 when absent) and `/PATH`.
fn split_url(url: &str) -> anyhow::Result<(String, &str)> {
    let Some(rest) = url.strip_prefix("http://") else {
        bail!("only http:// addresses are supported");
    };
    let (authority, path) = rest.find('/').map_or((rest, "/"), |i| rest.split_at(i));
    if authority.is_empty() {
        bail!("no host in the address");
    }
    let has_port = authority.rsplit_once(':').is_some_and(|(_, port)| port.parse::<u16>().is_ok());
    let authority = if has_port { authority.to_string() } else { format!("{authority}:80") };
    Ok((authority, path))
}

/// The code of an `HTTP/1.x CODE REASON` status line.
fn parse_status(head: &[u8]) -> anyhow::Result<u16> {
    let line = head.split(|&b| b == b'\n').next().unwrap_or_default();
    let line = String::from_utf8_lossy(line);
    let mut words = line.split_whitespace();
    match (words.next(), words.next().map(str::parse::<u16>)) {
        (Some(version), Some(Ok(code))) if version.starts_with("HTTP/") => Ok(code),
        _ => bail!("not an HTTP answer: {:?}", line.trim_end()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn urls_split_into_authority_and_path() {
        let (a, p) = split_url("http://127.0.0.1:8080/readyz").unwrap();
        assert_eq!((a.as_str(), p), ("127.0.0.1:8080", "/readyz"));
        let (a, p) = split_url("http://localhost").unwrap();
        assert_eq!((a.as_str(), p), ("localhost:80", "/"));
        let (a, _) = split_url("http://[::1]:9/x").unwrap();
        assert_eq!(a, "[::1]:9");
        assert!(split_url("https://x/").is_err());
        assert!(split_url("http:///readyz").is_err());
    }

    #[test]
    fn status_lines_give_their_code() {
        assert_eq!(parse_status(b"HTTP/1.1 200 OK\r\ncontent-length: 2\r\n\r\nok").unwrap(), 200);
        assert_eq!(parse_status(b"HTTP/1.0 503 Service Unavailable\r\n").unwrap(), 503);
        assert!(parse_status(b"SSH-2.0-OpenSSH\r\n").is_err());
        assert!(parse_status(b"").is_err());
    }
}
