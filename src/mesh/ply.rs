//! PLY (the Stanford polygon format): ASCII and binary of either byte order, any property
//! types, any element order. Reads the `vertex` element (x, y, z and, when all three are there,
//! nx, ny, nz) and the `face` element's `vertex_indices` (or `vertex_index`) lists; every other
//! element and property is skipped by its declared layout.

use std::fmt::Write as _;

use super::assemble::Assembler;
use super::text::{fields, parse};
use super::{Mesh, MeshError, ReadLimits};

const FORMAT: &str = "PLY";

fn malformed(message: impl Into<String>) -> MeshError {
    MeshError::malformed(FORMAT, message)
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Encoding {
    Ascii,
    BinaryLittleEndian,
    BinaryBigEndian,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Scalar {
    fn from_name(name: &[u8]) -> Option<Self> {
        Some(match name {
            b"char" | b"int8" => Self::I8,
            b"uchar" | b"uint8" => Self::U8,
            b"short" | b"int16" => Self::I16,
            b"ushort" | b"uint16" => Self::U16,
            b"int" | b"int32" => Self::I32,
            b"uint" | b"uint32" => Self::U32,
            b"float" | b"float32" => Self::F32,
            b"double" | b"float64" => Self::F64,
            _ => return None,
        })
    }

    fn size(self) -> usize {
        match self {
            Self::I8 | Self::U8 => 1,
            Self::I16 | Self::U16 => 2,
            Self::I32 | Self::U32 | Self::F32 => 4,
            Self::F64 => 8,
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Kind {
    Scalar(Scalar),
    List { count: Scalar, item: Scalar },
}

#[derive(Debug, Clone, PartialEq, Eq)]
struct Property {
    name: String,
    kind: Kind,
}

#[derive(Debug, Clone, PartialEq, Eq)]
struct Element {
    name: String,
    count: u64,
    properties: Vec<Property>,
}

impl Element {
    /// The fewest body bytes one instance can take in binary: lists may be empty.
    fn min_binary_size(&self) -> u64 {
        let size = |p: &Property| match p.kind {
            Kind::Scalar(s) | Kind::List { count: s, .. } => s.size() as u64,
        };
        self.properties.iter().map(size).sum()
    }

    fn property(&self, name: &str) -> Option<usize> {
        self.properties.iter().position(|p| p.name == name)
    }
}

#[derive(Debug)]
struct Header {
    encoding: Encoding,
    elements: Vec<Element>,
}

/// The header, and the offset where the body starts.
fn parse_header(bytes: &[u8]) -> Result<(Header, usize), MeshError> {
    let mut encoding = None;
    let mut elements: Vec<Element> = Vec::new();
    let mut pos = 0;
    let mut first = true;
    loop {
        let Some(len) = bytes[pos..].iter().position(|&b| b == b'\n') else {
            return Err(malformed("the header does not end with end_header"));
        };
        let line = &bytes[pos..pos + len];
        pos += len + 1;
        let mut f = fields(line);
        let keyword = f.next();
        if first {
            if keyword != Some(b"ply") || f.next().is_some() {
                return Err(malformed("the file does not start with \"ply\""));
            }
            first = false;
            continue;
        }
        match keyword {
            Some(b"format") => {
                encoding = Some(match f.next() {
                    Some(b"ascii") => Encoding::Ascii,
                    Some(b"binary_little_endian") => Encoding::BinaryLittleEndian,
                    Some(b"binary_big_endian") => Encoding::BinaryBigEndian,
                    other => return Err(malformed(format!("unknown format {:?}", lossy(other)))),
                });
            }
            Some(b"element") => {
                let (Some(name), Some(count), None) = (f.next(), f.next(), f.next()) else {
                    return Err(malformed(format!("bad element line {:?}", lossy(Some(line)))));
                };
                let count = parse::<u64>(count, FORMAT, "element count")?;
                elements.push(Element { name: lossy(Some(name)), count, properties: Vec::new() });
            }
            Some(b"property") => {
                let property = parse_property(line)?;
                let Some(element) = elements.last_mut() else {
                    return Err(malformed("a property before any element"));
                };
                element.properties.push(property);
            }
            Some(b"comment" | b"obj_info") | None => {}
            Some(b"end_header") => break,
            Some(other) => {
                return Err(malformed(format!("unknown header keyword {:?}", lossy(Some(other)))));
            }
        }
    }
    let encoding = encoding.ok_or_else(|| malformed("the header has no format line"))?;
    Ok((Header { encoding, elements }, pos))
}

fn parse_property(line: &[u8]) -> Result<Property, MeshError> {
    let mut f = fields(line).skip(1);
    let scalar = |name: Option<&[u8]>| {
        name.and_then(Scalar::from_name)
            .ok_or_else(|| malformed(format!("unknown property type in {:?}", lossy(Some(line)))))
    };
    let first = f.next();
    let kind = if first == Some(b"list") {
        Kind::List { count: scalar(f.next())?, item: scalar(f.next())? }
    } else {
        Kind::Scalar(scalar(first)?)
    };
    match (f.next(), f.next()) {
        (Some(name), None) => Ok(Property { name: lossy(Some(name)), kind }),
        _ => Err(malformed(format!("bad property line {:?}", lossy(Some(line))))),
    }
}

fn lossy(bytes: Option<&[u8]>) -> String {
    String::from_utf8_lossy(bytes.unwrap_or_default()).into_owned()
}

/// Where the body's values come from: binary bytes or ASCII tokens.
trait Values {
    fn scalar(&mut self, ty: Scalar) -> Result<f64, MeshError>;
    /// An upper bound on how many more values of type `ty` the body can hold: claimed counts
    /// above it are lies, caught before anything is allocated or looped over.
    fn room_for(&self, ty: Scalar) -> u64;
    /// An upper bound on how many more instances of `element` the body can hold.
    fn room_for_element(&self, element: &Element) -> u64;
    fn skip(&mut self, ty: Scalar, n: u64) -> Result<(), MeshError>;
}

struct Binary<'a> {
    body: &'a [u8],
    pos: usize,
    big_endian: bool,
}

impl Binary<'_> {
    fn take<const N: usize>(&mut self) -> Result<[u8; N], MeshError> {
        let bytes = self
            .body
            .get(self.pos..self.pos + N)
            .and_then(|b| <[u8; N]>::try_from(b).ok())
            .ok_or_else(|| malformed("the body ends early"))?;
        self.pos += N;
        Ok(bytes)
    }

    fn remaining(&self) -> u64 {
        (self.body.len() - self.pos.min(self.body.len())) as u64
    }
}

macro_rules! read_number {
    ($self:ident, $t:ty) => {{
        let b = $self.take::<{ std::mem::size_of::<$t>() }>()?;
        (if $self.big_endian { <$t>::from_be_bytes(b) } else { <$t>::from_le_bytes(b) }) as f64
    }};
}

impl Values for Binary<'_> {
    fn scalar(&mut self, ty: Scalar) -> Result<f64, MeshError> {
        Ok(match ty {
            Scalar::I8 => read_number!(self, i8),
            Scalar::U8 => read_number!(self, u8),
            Scalar::I16 => read_number!(self, i16),
            Scalar::U16 => read_number!(self, u16),
            Scalar::I32 => read_number!(self, i32),
            Scalar::U32 => read_number!(self, u32),
            Scalar::F32 => read_number!(self, f32),
            Scalar::F64 => read_number!(self, f64),
        })
    }

    fn room_for(&self, ty: Scalar) -> u64 {
        self.remaining() / ty.size() as u64
    }

    fn room_for_element(&self, element: &Element) -> u64 {
        self.remaining().checked_div(element.min_binary_size()).unwrap_or(u64::MAX)
    }

    fn skip(&mut self, ty: Scalar, n: u64) -> Result<(), MeshError> {
        let bytes = n.checked_mul(ty.size() as u64).filter(|&b| b <= self.remaining());
        let bytes = bytes.ok_or_else(|| malformed("the body ends early"))?;
        self.pos += bytes as usize;
        Ok(())
    }
}

struct Ascii<'a> {
    body: &'a [u8],
    pos: usize,
}

impl<'a> Ascii<'a> {
    fn token(&mut self) -> Result<&'a [u8], MeshError> {
        let rest = self.body.get(self.pos..).unwrap_or_default();
        let start = rest.iter().position(|b| !b.is_ascii_whitespace());
        let start = start.ok_or_else(|| malformed("the body ends early"))?;
        let len = rest[start..].iter().position(|b| b.is_ascii_whitespace());
        let len = len.unwrap_or(rest.len() - start);
        self.pos += start + len;
        Ok(&rest[start..start + len])
    }

    /// Every value takes at least one character and a separator.
    fn max_values(&self) -> u64 {
        (self.body.len().saturating_sub(self.pos) as u64).div_ceil(2)
    }
}

impl Values for Ascii<'_> {
    fn scalar(&mut self, _ty: Scalar) -> Result<f64, MeshError> {
        let token = self.token()?;
        parse(token, FORMAT, "value")
    }

    fn room_for(&self, _ty: Scalar) -> u64 {
        self.max_values()
    }

    fn room_for_element(&self, element: &Element) -> u64 {
        self.max_values().checked_div(element.properties.len() as u64).unwrap_or(u64::MAX)
    }

    fn skip(&mut self, _ty: Scalar, n: u64) -> Result<(), MeshError> {
        for _ in 0..n {
            self.token()?;
        }
        Ok(())
    }
}

pub(crate) fn read(bytes: &[u8], limits: &ReadLimits) -> Result<Mesh, MeshError> {
    let (header, body_start) = parse_header(bytes)?;
    let body = &bytes[body_start..];
    match header.encoding {
        Encoding::Ascii => read_body(&header, &mut Ascii { body, pos: 0 }, limits),
        Encoding::BinaryLittleEndian => {
            read_body(&header, &mut Binary { body, pos: 0, big_endian: false }, limits)
        }
        Encoding::BinaryBigEndian => {
            read_body(&header, &mut Binary { body, pos: 0, big_endian: true }, limits)
        }
    }
}

fn read_body(
    header: &Header,
    values: &mut impl Values,
    limits: &ReadLimits,
) -> Result<Mesh, MeshError> {
    let mut asm = Assembler::new(FORMAT, limits);
    let mut normals = None;
    let (mut seen_vertices, mut seen_faces) = (false, false);
    for element in &header.elements {
        match element.name.as_str() {
            "vertex" | "face" if element.properties.is_empty() && element.count > 0 => {
                return Err(malformed(format!("element {} has no properties", element.name)));
            }
            "vertex" if !seen_vertices => {
                seen_vertices = true;
                normals = read_vertices(element, values, &mut asm)?;
            }
            "face" if !seen_faces => {
                seen_faces = true;
                read_faces(element, values, &mut asm)?;
            }
            "vertex" | "face" => {
                return Err(malformed(format!("more than one {} element", element.name)));
            }
            _ => skip_element(element, values)?,
        }
    }
    asm.finish(normals)
}

/// Checks an element's claimed count against the room left in the body, so that the loops
/// and allocations that follow are bounded by the input's size.
fn check_room(element: &Element, values: &impl Values) -> Result<(), MeshError> {
    let room = values.room_for_element(element);
    if element.count > room {
        return Err(malformed(format!(
            "the header claims {} {} elements, the body holds at most {room}",
            element.count, element.name
        )));
    }
    Ok(())
}

fn skip_element(element: &Element, values: &mut impl Values) -> Result<(), MeshError> {
    if element.properties.is_empty() {
        return Ok(());
    }
    check_room(element, values)?;
    for _ in 0..element.count {
        for p in &element.properties {
            skip_property(p.kind, values)?;
        }
    }
    Ok(())
}

fn skip_property(kind: Kind, values: &mut impl Values) -> Result<(), MeshError> {
    match kind {
        Kind::Scalar(ty) => values.skip(ty, 1),
        Kind::List { count, item } => {
            let n = list_length(values, count, item)?;
            values.skip(item, n)
        }
    }
}

/// A list's length, which must be a whole number that the rest of the body can hold.
fn list_length(values: &mut impl Values, count: Scalar, item: Scalar) -> Result<u64, MeshError> {
    let n = values.scalar(count)?;
    if n.fract() != 0.0 || n < 0.0 || n > values.room_for(item) as f64 {
        return Err(malformed(format!("bad list length {n}")));
    }
    Ok(n as u64)
}

/// Reads the vertex element; returns the normals when it has nx, ny and nz.
fn read_vertices(
    element: &Element,
    values: &mut impl Values,
    asm: &mut Assembler,
) -> Result<Option<Vec<[f32; 3]>>, MeshError> {
    // Where each property goes: 0..3 position, 3..6 normal, None skipped.
    let scalar_slot = |name: &str| {
        let i = element.property(name)?;
        matches!(element.properties[i].kind, Kind::Scalar(_)).then_some(i)
    };
    let position = ["x", "y", "z"].map(scalar_slot);
    let [Some(_), Some(_), Some(_)] = position else {
        return Err(malformed("the vertex element lacks scalar x, y and z properties"));
    };
    let normal = ["nx", "ny", "nz"].map(scalar_slot);
    let has_normals = normal.iter().all(Option::is_some);
    let mut slot_of = vec![None; element.properties.len()];
    for (slot, property) in
        position.iter().chain(if has_normals { &normal[..] } else { &[] }).enumerate()
    {
        if let Some(p) = property {
            slot_of[*p] = Some(slot);
        }
    }

    asm.check_limits(element.count, 0)?;
    check_room(element, values)?;
    asm.reserve(element.count, 0)?;
    let mut normals = has_normals.then(|| Vec::with_capacity(element.count as usize));
    let mut v = [0.0f64; 6];
    for _ in 0..element.count {
        for (property, slot) in element.properties.iter().zip(&slot_of) {
            match (property.kind, slot) {
                (Kind::Scalar(ty), Some(slot)) => v[*slot] = values.scalar(ty)?,
                (kind, _) => skip_property(kind, values)?,
            }
        }
        asm.push_vertex([v[0] as f32, v[1] as f32, v[2] as f32])?;
        if let Some(normals) = &mut normals {
            normals.push([v[3] as f32, v[4] as f32, v[5] as f32]);
        }
    }
    Ok(normals)
}

fn read_faces(
    element: &Element,
    values: &mut impl Values,
    asm: &mut Assembler,
) -> Result<(), MeshError> {
    let indices = element.property("vertex_indices").or_else(|| element.property("vertex_index"));
    let indices = indices.filter(|&i| matches!(element.properties[i].kind, Kind::List { .. }));
    let Some(indices) = indices else {
        return Err(malformed("the face element lacks a vertex_indices list"));
    };
    // Most faces are triangles; polygons grow the triangle list past this as they come.
    asm.check_limits(0, element.count)?;
    check_room(element, values)?;
    asm.reserve(0, element.count)?;
    let mut polygon = Vec::new();
    for _ in 0..element.count {
        for (i, property) in element.properties.iter().enumerate() {
            match property.kind {
                Kind::List { count, item } if i == indices => {
                    let n = list_length(values, count, item)?;
                    polygon.clear();
                    for _ in 0..n {
                        polygon.push(vertex_index(values.scalar(item)?)?);
                    }
                }
                kind => skip_property(kind, values)?,
            }
        }
        asm.push_polygon(&polygon)?;
    }
    Ok(())
}

fn vertex_index(value: f64) -> Result<u32, MeshError> {
    if value.fract() != 0.0 || value < 0.0 || value > u32::MAX as f64 {
        return Err(malformed(format!("bad vertex index {value}")));
    }
    Ok(value as u32)
}

/// Binary little-endian PLY: float x, y, z (and nx, ny, nz when the mesh has normals), and,
/// unless the mesh is a point cloud, a face element of `list uchar int vertex_indices`.
pub(crate) fn write(mesh: &Mesh) -> Result<Vec<u8>, MeshError> {
    if i32::try_from(mesh.vertices.len()).is_err() {
        return Err(MeshError::invalid("PLY int indices cannot address that many vertices"));
    }
    let mut header = String::from("ply\nformat binary_little_endian 1.0\ncomment meshstream\n");
    // Writing to a String cannot fail; the results are discarded for that reason only.
    let _ = writeln!(header, "element vertex {}", mesh.vertices.len());
    header.push_str("property float x\nproperty float y\nproperty float z\n");
    if mesh.normals.is_some() {
        header.push_str("property float nx\nproperty float ny\nproperty float nz\n");
    }
    if !mesh.is_point_cloud() {
        let _ = writeln!(header, "element face {}", mesh.faces.len());
        header.push_str("property list uchar int vertex_indices\n");
    }
    header.push_str("end_header\n");

    let vertex_size = if mesh.normals.is_some() { 24 } else { 12 };
    let mut out = Vec::with_capacity(
        header.len() + vertex_size * mesh.vertices.len() + 13 * mesh.faces.len(),
    );
    out.extend_from_slice(header.as_bytes());
    for (i, v) in mesh.vertices.iter().enumerate() {
        let normal = mesh.normals.as_ref().and_then(|n| n.get(i));
        for c in v.iter().chain(normal.into_iter().flatten()) {
            out.extend_from_slice(&c.to_le_bytes());
        }
    }
    for f in &mesh.faces {
        out.push(3);
        for &i in f {
            // Fits: checked above against the vertex count, which bounds valid indices.
            out.extend_from_slice(&(i as i32).to_le_bytes());
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn read_bytes(b: &[u8]) -> Result<Mesh, MeshError> {
        read(b, &ReadLimits::default())
    }

    /// A binary PLY of a unit square (two triangles as one quad) with extra properties and
    /// elements around the ones we read.
    fn binary_square(big_endian: bool) -> Vec<u8> {
        let order = if big_endian { "big" } else { "little" };
        let mut out = format!(
            "ply\r\nformat binary_{order}_endian 1.0\r\ncomment made by hand\r\n\
             element material 1\r\nproperty list ushort double params\r\nproperty uchar id\r\n\
             element vertex 4\r\nproperty double confidence\r\nproperty float x\r\n\
             property short flags\r\nproperty float y\r\nproperty float z\r\n\
             property list uint char tags\r\n\
             element face 1\r\nproperty int material\r\nproperty list int uint vertex_indices\r\n\
             end_header\r\n"
        )
        .into_bytes();
        macro_rules! put {
            ($v:expr) => {
                out.extend_from_slice(&if big_endian { $v.to_be_bytes() } else { $v.to_le_bytes() })
            };
        }
        put!(2u16);
        put!(1.5f64);
        put!(2.5f64);
        put!(7u8);
        for (i, [x, y]) in
            [[0.0f32, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]].into_iter().enumerate()
        {
            put!(0.5f64);
            put!(x);
            put!(-1i16);
            put!(y);
            put!(2.0f32);
            put!(i as u32);
            for _ in 0..i {
                put!(-3i8);
            }
        }
        put!(9i32);
        put!(4i32);
        for i in 0..4u32 {
            put!(i);
        }
        out
    }

    fn assert_square(mesh: &Mesh) {
        assert_eq!(
            mesh.vertices,
            vec![[0.0, 0.0, 2.0], [1.0, 0.0, 2.0], [1.0, 1.0, 2.0], [0.0, 1.0, 2.0]]
        );
        assert_eq!(mesh.faces, vec![[0, 1, 2], [0, 2, 3]]);
    }

    #[test]
    fn binary_both_byte_orders_with_extra_properties_and_elements() {
        for big_endian in [false, true] {
            let mesh = read_bytes(&binary_square(big_endian)).unwrap();
            assert_square(&mesh);
            assert!(mesh.normals.is_none());
        }
    }

    #[test]
    fn ascii_with_normals_faces_first_and_vertex_index() {
        let text = "ply\nformat ascii 1.0\nelement face 1\nproperty list uchar int vertex_index\n\
                    element vertex 4\nproperty float x\nproperty float y\nproperty float z\n\
                    property float nx\nproperty float ny\nproperty float nz\nproperty uchar red\n\
                    element edge 2\nproperty int vertex1\nproperty int vertex2\n\
                    end_header\n4 0 1 2 3\n0 0 2 0 0 1 255\n1 0 2 0 0 1 0\n1 1 2\n0 0 1 9\n\
                    0 1 2 0 0 1 1\n0 1\n1 2\n";
        let mesh = read_bytes(text.as_bytes()).unwrap();
        assert_square(&mesh);
        assert_eq!(mesh.normals, Some(vec![[0.0, 0.0, 1.0]; 4]));
    }

    #[test]
    fn point_cloud_without_faces() {
        let text = "ply\nformat ascii 1.0\nelement vertex 2\nproperty double x\n\
                    property double y\nproperty double z\nend_header\n1 2 3\n4 5 6\n";
        let mesh = read_bytes(text.as_bytes()).unwrap();
        assert!(mesh.is_point_cloud());
        assert_eq!(mesh.vertices, vec![[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]);
    }

    #[test]
    fn lies_and_truncations_are_malformed() {
        let good = binary_square(false);
        for cut in [good.len() - 1, good.len() - 20, 200, 100, 10, 0] {
            let err = read_bytes(&good[..cut]).unwrap_err();
            assert!(matches!(err, MeshError::Malformed { .. }), "cut at {cut}: {err}");
        }
        let head = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n\
                    property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n";
        for body in [
            "0 0 0\n1 0 0\n0 1 0\n3 0 1 3\n",
            "0 0 0\n1 0 0\nnan 1 0\n3 0 1 2\n",
            "0 0 0\n1 0 0\n0 1 0\n3 0 1 -2\n",
            "0 0 0\n1 0 0\n0 1 0\n2 0 1\n",
            "0 0 0\n1 0 0\n0 1 0\n3 0 1.5 2\n",
        ] {
            let err = read_bytes(format!("{head}{body}").as_bytes()).unwrap_err();
            assert!(matches!(err, MeshError::Malformed { .. }), "{body:?}: {err}");
        }
        for header in [
            "plyx\n",
            "ply\nelement vertex 1\nend_header\n",
            "ply\nformat ascii 1.0\nproperty float x\nend_header\n",
            "ply\nformat ascii 1.0\nelement vertex 1\nproperty float128 x\nend_header\n",
            "ply\nformat ascii 1.0\n",
        ] {
            assert!(
                matches!(read_bytes(header.as_bytes()), Err(MeshError::Malformed { .. })),
                "{header:?}"
            );
        }
    }

    #[test]
    fn huge_claims_fail_before_allocating() {
        for count in [1u64 << 31, u64::MAX] {
            for format in ["ascii", "binary_little_endian"] {
                let text = format!(
                    "ply\nformat {format} 1.0\nelement vertex {count}\nproperty float x\n\
                     property float y\nproperty float z\nelement junk {count}\nproperty int a\n\
                     end_header\n0 0 0\n"
                );
                let unlimited = ReadLimits {
                    max_bytes: u64::MAX,
                    max_vertices: usize::MAX,
                    max_faces: usize::MAX,
                };
                assert!(matches!(
                    read(text.as_bytes(), &unlimited),
                    Err(MeshError::Malformed { .. })
                ));
                assert!(matches!(read_bytes(text.as_bytes()), Err(MeshError::TooLarge { .. })));
            }
        }
        // A list that claims 2^32 - 1 entries.
        let mut b = b"ply\nformat binary_little_endian 1.0\nelement face 1\nproperty list uint int vertex_indices\nend_header\n".to_vec();
        b.extend_from_slice(&u32::MAX.to_le_bytes());
        assert!(matches!(read_bytes(&b), Err(MeshError::Malformed { .. })));
    }

    #[test]
    fn write_then_read_keeps_everything() {
        let mut mesh = Mesh::new(
            vec![[0.1, -2.5, 3e-7], [1.0, 0.0, 1e20], [0.0, 1.0, 0.0]],
            vec![[0, 1, 2], [2, 1, 0]],
        );
        assert_eq!(read_bytes(&write(&mesh).unwrap()).unwrap(), mesh);
        mesh.normals = Some(vec![[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]);
        assert_eq!(read_bytes(&write(&mesh).unwrap()).unwrap(), mesh);
        mesh.faces.clear();
        let written = write(&mesh).unwrap();
        assert!(!String::from_utf8_lossy(&written).contains("element face"));
        assert_eq!(read_bytes(&written).unwrap(), mesh);
    }
}
