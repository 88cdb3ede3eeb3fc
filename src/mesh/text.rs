//! Splitting and number parsing shared by the text formats (OBJ, ASCII PLY, ASCII STL),
//! working on bytes so that no line is copied and no encoding is assumed.

use super::MeshError;

/// The lines of a text, without their `\n` or `\r\n`.
pub(crate) fn lines(text: &[u8]) -> impl Iterator<Item = &[u8]> {
    text.split(|&b| b == b'\n').map(|line| line.strip_suffix(b"\r").unwrap_or(line))
}

/// The whitespace-separated fields of a line (or of a whole text).
pub(crate) fn fields(text: &[u8]) -> impl Iterator<Item = &[u8]> {
    text.split(|b| b.is_ascii_whitespace()).filter(|f| !f.is_empty())
}

/// A field as a number of type `T` (`f32`, `f64`, `i64`...), or a `Malformed` error naming it.
pub(crate) fn parse<T: std::str::FromStr>(
    field: &[u8],
    format: &'static str,
    what: &str,
) -> Result<T, MeshError> {
    std::str::from_utf8(field).ok().and_then(|s| s.parse().ok()).ok_or_else(|| {
        MeshError::malformed(
            format,
            format!("{what}: cannot read {:?} as a number", String::from_utf8_lossy(field)),
        )
    })
}

/// The next field as an `f32`, or an error when the line ends early.
pub(crate) fn next_f32<'a>(
    fields: &mut impl Iterator<Item = &'a [u8]>,
    format: &'static str,
    what: &str,
) -> Result<f32, MeshError> {
    let field = fields
        .next()
        .ok_or_else(|| MeshError::malformed(format, format!("{what}: too few numbers")))?;
    parse(field, format, what)
}

/// Three `f32` fields, for a position or a normal.
pub(crate) fn next_vec3<'a>(
    fields: &mut impl Iterator<Item = &'a [u8]>,
    format: &'static str,
    what: &str,
) -> Result<[f32; 3], MeshError> {
    Ok([
        next_f32(fields, format, what)?,
        next_f32(fields, format, what)?,
        next_f32(fields, format, what)?,
    ])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lines_and_fields_ignore_crlf_and_runs_of_spaces() {
        let text = b"v 1  2\t3\r\nf 1 2 3\n";
        let all: Vec<Vec<&[u8]>> = lines(text).map(|l| fields(l).collect()).collect();
        assert_eq!(all[0], vec![&b"v"[..], b"1", b"2", b"3"]);
        assert_eq!(all[1], vec![&b"f"[..], b"1", b"2", b"3"]);
        assert!(all[2].is_empty());
    }

    #[test]
    fn numbers_parse_or_fail_with_a_typed_error() {
        let mut f = fields(b"1.5 -2e3 x");
        assert_eq!(next_f32(&mut f, "T", "v").unwrap(), 1.5);
        assert_eq!(next_f32(&mut f, "T", "v").unwrap(), -2000.0);
        assert!(matches!(next_f32(&mut f, "T", "v"), Err(MeshError::Malformed { .. })));
        assert!(next_f32(&mut f, "T", "v").is_err());
        assert!(parse::<i64>(b"\xff", "T", "f").is_err());
    }
}
