//! Gaussian sets in the original 3DGS PLY layout, so our splats open in standard
//! viewers and in python `plyfile`, and theirs open here.
//!
//! Written: binary little-endian float32 with the properties
//! `x y z nx ny nz f_dc_0..2 f_rest_0..(3*(K-1)-1) opacity scale_0..2 rot_0..3`,
//! raw values (log scale, opacity logit, wxyz quaternion). `f_rest` is
//! channel-major in the file (`f_rest[c*(K-1) + k-1]`) while [`GaussianSet`]
//! keeps it coefficient-major (`[k-1][c]`).
//!
//! Read: any PLY whose `vertex` element has those properties, in any order, as
//! `float`/`float32` or `double`/`float64`; extra properties and other elements
//! are ignored; binary little/big endian and ascii bodies. The SH degree comes
//! from the number of `f_rest_*` properties (0, 9, 24 or 45).

use std::path::Path;

use super::{sh_coeffs, GaussianSet, ParamGroup};
use crate::error::{write_atomic, Error, Result};

/// Write `set` to `path` atomically.
pub fn write_ply(path: &Path, set: &GaussianSet) -> Result<()> {
    set.check_shapes().map_err(|m| Error::bad_file(path, format!("cannot write an inconsistent Gaussian set: {m}")))?;
    write_atomic(path, &encode_ply(set))
}

/// Read a Gaussian set from `path`.
pub fn read_ply(path: &Path) -> Result<GaussianSet> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    decode_ply(&bytes, path)
}

/// Property names in the order they are written for SH degree `degree`.
fn property_names(degree: u32) -> Vec<String> {
    let n_rest = (sh_coeffs(degree) - 1) * 3;
    let mut names: Vec<String> =
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"].map(String::from).into();
    names.extend((0..n_rest).map(|i| format!("f_rest_{i}")));
    names.push("opacity".into());
    names.extend((0..3).map(|i| format!("scale_{i}")));
    names.extend((0..4).map(|i| format!("rot_{i}")));
    names
}

/// Encode `set` (which must have consistent shapes) as a binary little-endian PLY.
pub fn encode_ply(set: &GaussianSet) -> Vec<u8> {
    let names = property_names(set.sh_degree);
    let n = set.len();
    let mut out = format!("ply\nformat binary_little_endian 1.0\nelement vertex {n}\n").into_bytes();
    for name in &names {
        out.extend_from_slice(format!("property float {name}\n").as_bytes());
    }
    out.extend_from_slice(b"end_header\n");
    let rest_k = sh_coeffs(set.sh_degree) - 1;
    out.reserve(n * names.len() * 4);
    let mut row = Vec::with_capacity(names.len());
    for i in 0..n {
        row.clear();
        row.extend_from_slice(&set.means[3 * i..3 * i + 3]);
        row.extend_from_slice(&[0.0; 3]);
        row.extend_from_slice(&set.sh_dc[3 * i..3 * i + 3]);
        let rest = &set.sh_rest[3 * rest_k * i..3 * rest_k * (i + 1)];
        for c in 0..3 {
            row.extend((0..rest_k).map(|k| rest[3 * k + c]));
        }
        row.push(set.opacity_logits[i]);
        row.extend_from_slice(&set.log_scales[3 * i..3 * i + 3]);
        row.extend_from_slice(&set.rotations[4 * i..4 * i + 4]);
        for v in &row {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    out
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Format {
    Ascii,
    BinaryLe,
    BinaryBe,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
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
    fn parse(name: &str) -> Option<Scalar> {
        Some(match name {
            "char" | "int8" => Scalar::I8,
            "uchar" | "uint8" => Scalar::U8,
            "short" | "int16" => Scalar::I16,
            "ushort" | "uint16" => Scalar::U16,
            "int" | "int32" => Scalar::I32,
            "uint" | "uint32" => Scalar::U32,
            "float" | "float32" => Scalar::F32,
            "double" | "float64" => Scalar::F64,
            _ => return None,
        })
    }

    /// The PLY spelling, for error messages.
    fn name(self) -> &'static str {
        match self {
            Scalar::I8 => "char",
            Scalar::U8 => "uchar",
            Scalar::I16 => "short",
            Scalar::U16 => "ushort",
            Scalar::I32 => "int",
            Scalar::U32 => "uint",
            Scalar::F32 => "float",
            Scalar::F64 => "double",
        }
    }

    fn size(self) -> usize {
        match self {
            Scalar::I8 | Scalar::U8 => 1,
            Scalar::I16 | Scalar::U16 => 2,
            Scalar::I32 | Scalar::U32 | Scalar::F32 => 4,
            Scalar::F64 => 8,
        }
    }

    fn is_float(self) -> bool {
        matches!(self, Scalar::F32 | Scalar::F64)
    }
}

#[derive(Clone, Debug)]
enum PropType {
    Scalar(Scalar),
    List { count: Scalar, item: Scalar },
}

#[derive(Clone, Debug)]
struct Property {
    name: String,
    ty: PropType,
}

#[derive(Clone, Debug)]
struct Element {
    name: String,
    count: usize,
    props: Vec<Property>,
}

struct Header {
    format: Format,
    elements: Vec<Element>,
    body_start: usize,
}

fn parse_header(bytes: &[u8], path: &Path) -> Result<Header> {
    let bad = |msg: String| Error::bad_file(path, format!("bad PLY header: {msg}"));
    if !bytes.starts_with(b"ply\n") && !bytes.starts_with(b"ply\r\n") {
        return Err(bad("the file does not start with the 'ply' magic line".into()));
    }
    let end = find(bytes, b"\nend_header").ok_or_else(|| bad("no 'end_header' line".into()))? + 1;
    let mut body_start = end + b"end_header".len();
    if bytes[body_start..].starts_with(b"\r\n") {
        body_start += 2;
    } else if bytes[body_start..].starts_with(b"\n") {
        body_start += 1;
    } else {
        return Err(bad("'end_header' is not followed by a line break".into()));
    }
    let text = std::str::from_utf8(&bytes[..end]).map_err(|_| bad("the header is not text".into()))?;
    let mut format = None;
    let mut elements: Vec<Element> = Vec::new();
    for (lineno, line) in text.lines().enumerate().skip(1) {
        let words: Vec<&str> = line.split_whitespace().collect();
        let at = |msg: &str| bad(format!("line {}: {msg}: '{}'", lineno + 1, line.trim()));
        match words.as_slice() {
            [] => {}
            ["comment" | "obj_info", ..] => {}
            ["format", kind, _version] => {
                format = Some(match *kind {
                    "ascii" => Format::Ascii,
                    "binary_little_endian" => Format::BinaryLe,
                    "binary_big_endian" => Format::BinaryBe,
                    _ => return Err(at("unknown format")),
                });
            }
            ["element", name, count] => {
                let count = count.parse().map_err(|_| at("bad element count"))?;
                elements.push(Element { name: name.to_string(), count, props: Vec::new() });
            }
            ["property", "list", count, item, name] => {
                let el = elements.last_mut().ok_or_else(|| at("property before any element"))?;
                let count = Scalar::parse(count).filter(|s| !s.is_float()).ok_or_else(|| at("bad list count type"))?;
                let item = Scalar::parse(item).ok_or_else(|| at("unknown type"))?;
                el.props.push(Property { name: name.to_string(), ty: PropType::List { count, item } });
            }
            ["property", ty, name] => {
                let el = elements.last_mut().ok_or_else(|| at("property before any element"))?;
                let ty = Scalar::parse(ty).ok_or_else(|| at("unknown type"))?;
                el.props.push(Property { name: name.to_string(), ty: PropType::Scalar(ty) });
            }
            _ => return Err(at("unrecognised line")),
        }
    }
    let format = format.ok_or_else(|| bad("no 'format' line".into()))?;
    Ok(Header { format, elements, body_start })
}

fn find(hay: &[u8], needle: &[u8]) -> Option<usize> {
    hay.windows(needle.len()).position(|w| w == needle)
}

/// Reads scalars from the body, in either encoding.
struct Body<'a> {
    bytes: &'a [u8],
    pos: usize,
    format: Format,
}

impl Body<'_> {
    /// Next value as f64, or None at the end of the data (or on an unparsable ascii token).
    fn next(&mut self, ty: Scalar) -> Option<f64> {
        match self.format {
            Format::Ascii => {
                let rest = &self.bytes[self.pos..];
                let start = rest.iter().position(|b| !b.is_ascii_whitespace())?;
                let len = rest[start..].iter().position(|b| b.is_ascii_whitespace()).unwrap_or(rest.len() - start);
                self.pos += start + len;
                let token = std::str::from_utf8(&rest[start..start + len]).ok()?;
                if ty.is_float() {
                    token.parse::<f64>().ok()
                } else {
                    token.parse::<i64>().ok().map(|v| v as f64)
                }
            }
            Format::BinaryLe | Format::BinaryBe => {
                let n = ty.size();
                let raw = self.bytes.get(self.pos..self.pos + n)?;
                self.pos += n;
                let mut b = [0u8; 8];
                b[..n].copy_from_slice(raw);
                if self.format == Format::BinaryBe {
                    b[..n].reverse();
                }
                Some(match ty {
                    Scalar::I8 => b[0] as i8 as f64,
                    Scalar::U8 => b[0] as f64,
                    Scalar::I16 => i16::from_le_bytes([b[0], b[1]]) as f64,
                    Scalar::U16 => u16::from_le_bytes([b[0], b[1]]) as f64,
                    Scalar::I32 => i32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
                    Scalar::U32 => u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
                    Scalar::F32 => f32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
                    Scalar::F64 => f64::from_le_bytes(b),
                })
            }
        }
    }
}

/// Where each value of a vertex row goes in the Gaussian set.
#[derive(Clone, Copy)]
enum Slot {
    Ignore,
    /// Group, offset within the row of that group.
    Field(ParamGroup, usize),
}

/// Map a vertex property name to its slot; `rest_k` is the SH rest count per channel.
fn slot_for(name: &str, rest_k: usize) -> Slot {
    let indexed = |prefix: &str| name.strip_prefix(prefix).and_then(|s| s.parse::<usize>().ok());
    match name {
        "x" => Slot::Field(ParamGroup::Means, 0),
        "y" => Slot::Field(ParamGroup::Means, 1),
        "z" => Slot::Field(ParamGroup::Means, 2),
        "opacity" => Slot::Field(ParamGroup::OpacityLogits, 0),
        _ => {
            if let Some(i) = indexed("f_dc_").filter(|&i| i < 3) {
                Slot::Field(ParamGroup::ShDc, i)
            } else if let Some(i) = indexed("scale_").filter(|&i| i < 3) {
                Slot::Field(ParamGroup::LogScales, i)
            } else if let Some(i) = indexed("rot_").filter(|&i| i < 4) {
                Slot::Field(ParamGroup::Rotations, i)
            } else if let Some(i) = indexed("f_rest_").filter(|&i| i < 3 * rest_k) {
                // File: channel-major c*(K-1) + (k-1); set: [k-1][c].
                let (c, k) = (i / rest_k, i % rest_k);
                Slot::Field(ParamGroup::ShRest, 3 * k + c)
            } else {
                Slot::Ignore
            }
        }
    }
}

/// Position of the 'vertex' element.
fn vertex_index(header: &Header, path: &Path) -> Result<usize> {
    header
        .elements
        .iter()
        .position(|e| e.name == "vertex")
        .ok_or_else(|| Error::bad_file(path, "the PLY has no 'vertex' element"))
}

fn truncated_error(path: &Path, el: &Element, row: usize) -> Error {
    Error::bad_file(path, format!("truncated or malformed body: element '{}' row {row} of {}", el.name, el.count))
}

/// A reader positioned at the vertex rows (the elements stored before them skipped).
fn body_at_vertices<'a>(bytes: &'a [u8], header: &Header, vi: usize, path: &Path) -> Result<Body<'a>> {
    let mut body = Body { bytes, pos: header.body_start, format: header.format };
    for el in &header.elements[..vi] {
        read_rows(&mut body, el, |_, _| Ok(())).map_err(|row| truncated_error(path, el, row))??;
    }
    Ok(body)
}

/// Decode a PLY file's bytes; `path` is only used in error messages.
pub fn decode_ply(bytes: &[u8], path: &Path) -> Result<GaussianSet> {
    let header = parse_header(bytes, path)?;
    let bad = |msg: String| Error::bad_file(path, msg);
    let vi = vertex_index(&header, path)?;
    let vertex = &header.elements[vi];

    // SH degree from the f_rest count; they must be f_rest_0..f_rest_{n-1}.
    let rest: Vec<usize> = vertex
        .props
        .iter()
        .filter_map(|p| p.name.strip_prefix("f_rest_").and_then(|s| s.parse::<usize>().ok()))
        .collect();
    let n_rest = rest.len();
    let degree = (0..=3u32)
        .find(|&d| (sh_coeffs(d) - 1) * 3 == n_rest)
        .ok_or_else(|| bad(format!("{n_rest} f_rest_* properties; expected 0, 9, 24 or 45 (SH degree 0..3)")))?;
    let rest_k = sh_coeffs(degree) - 1;

    let mut set = GaussianSet::new(degree);
    let mut slots = Vec::with_capacity(vertex.props.len());
    let mut seen: Vec<(ParamGroup, usize)> = Vec::new();
    for p in &vertex.props {
        let slot = slot_for(&p.name, rest_k);
        if let Slot::Field(g, off) = slot {
            match p.ty {
                PropType::Scalar(s) if s.is_float() => {}
                PropType::Scalar(s) => {
                    return Err(bad(format!(
                        "vertex property '{}' has type {}; expected float or double",
                        p.name,
                        s.name()
                    )));
                }
                PropType::List { .. } => {
                    return Err(bad(format!("vertex property '{}' is a list; expected float", p.name)));
                }
            }
            if seen.contains(&(g, off)) {
                return Err(bad(format!("vertex property '{}' appears twice", p.name)));
            }
            seen.push((g, off));
        }
        slots.push(slot);
    }
    let missing: Vec<String> = property_names(degree)
        .into_iter()
        .filter(|n| !["nx", "ny", "nz"].contains(&n.as_str()))
        .filter(|n| match slot_for(n, rest_k) {
            Slot::Field(g, off) => !seen.contains(&(g, off)),
            Slot::Ignore => false,
        })
        .collect();
    if !missing.is_empty() {
        return Err(bad(format!("vertex element lacks properties: {}", missing.join(", "))));
    }

    let mut body = body_at_vertices(bytes, &header, vi, path)?;
    let truncated = |el: &Element, row: usize| truncated_error(path, el, row);

    let n = vertex.count;
    // Refuse counts the body cannot hold before allocating for them.
    let min_row_bytes: usize = vertex
        .props
        .iter()
        .map(|p| match (header.format, &p.ty) {
            (Format::Ascii, _) => 1,
            (_, PropType::Scalar(s)) => s.size(),
            (_, PropType::List { count, .. }) => count.size(),
        })
        .sum();
    if n.saturating_mul(min_row_bytes) > bytes.len().saturating_sub(body.pos) {
        return Err(truncated(vertex, bytes.len().saturating_sub(body.pos) / min_row_bytes.max(1)));
    }
    for g in ParamGroup::ALL {
        let w = set.width(g);
        set.group_mut(g).resize(n * w, 0.0);
    }
    read_rows(&mut body, vertex, |row, (pi, v)| {
        if let Slot::Field(g, off) = slots[pi] {
            let v32 = v as f32;
            if !v32.is_finite() {
                return Err(bad(format!(
                    "vertex {row}: property '{}' is {v} (not a finite float)",
                    vertex.props[pi].name
                )));
            }
            let w = set.width(g);
            set.group_mut(g)[row * w + off] = v32;
        }
        Ok(())
    })
    .map_err(|row| truncated(vertex, row))??;
    Ok(set)
}

/// A plain point cloud: positions and, when the file has them, colours in [0, 1].
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PointCloud {
    pub points: Vec<glam::Vec3>,
    pub colors: Option<Vec<glam::Vec3>>,
}

/// Read a point-cloud PLY (any format and numeric types): `x y z` and, when
/// present, `red green blue` (integers scaled from 0..255, floats taken as 0..1).
pub fn read_point_cloud(path: &Path) -> Result<PointCloud> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    decode_point_cloud(&bytes, path)
}

/// Decode a point-cloud PLY's bytes; `path` is only used in error messages.
pub fn decode_point_cloud(bytes: &[u8], path: &Path) -> Result<PointCloud> {
    let header = parse_header(bytes, path)?;
    let bad = |msg: String| Error::bad_file(path, msg);
    let vi = vertex_index(&header, path)?;
    let vertex = &header.elements[vi];
    let find = |name: &str| vertex.props.iter().position(|p| p.name == name);
    let (Some(_), Some(_), Some(_)) = (find("x"), find("y"), find("z")) else {
        return Err(bad("vertex element lacks x, y or z".into()));
    };
    let has_color = ["red", "green", "blue"].iter().all(|c| find(c).is_some());
    // Column of each property: 0..3 position, 3..6 colour, else ignored.
    let column: Vec<Option<usize>> = vertex
        .props
        .iter()
        .map(|p| match p.name.as_str() {
            "x" => Some(0),
            "y" => Some(1),
            "z" => Some(2),
            "red" if has_color => Some(3),
            "green" if has_color => Some(4),
            "blue" if has_color => Some(5),
            _ => None,
        })
        .collect();
    let color_scale: Vec<f64> = vertex
        .props
        .iter()
        .map(|p| match p.ty {
            PropType::Scalar(s) if !s.is_float() => 1.0 / 255.0,
            _ => 1.0,
        })
        .collect();
    let mut body = body_at_vertices(bytes, &header, vi, path)?;
    let truncated = |el: &Element, row: usize| truncated_error(path, el, row);
    // Every row takes at least one byte: refuse counts the file cannot hold before allocating.
    if vertex.count > bytes.len() {
        return Err(truncated(vertex, 0));
    }
    let mut values = vec![[0.0f32; 6]; vertex.count];
    read_rows(&mut body, vertex, |row, (pi, v)| {
        if let Some(c) = column[pi] {
            let v = (if c >= 3 { v * color_scale[pi] } else { v }) as f32;
            if !v.is_finite() {
                return Err(bad(format!("vertex {row}: property '{}' is not a finite number", vertex.props[pi].name)));
            }
            values[row][c] = v;
        }
        Ok(())
    })
    .map_err(|row| truncated(vertex, row))??;
    Ok(PointCloud {
        points: values.iter().map(|v| glam::Vec3::new(v[0], v[1], v[2])).collect(),
        colors: has_color.then(|| values.iter().map(|v| glam::Vec3::new(v[3], v[4], v[5])).collect()),
    })
}

/// Read every row of `el`, calling `f(row, (property index, value))` for each scalar
/// property. Outer error: the row where the data ran out or did not parse.
fn read_rows(
    body: &mut Body,
    el: &Element,
    mut f: impl FnMut(usize, (usize, f64)) -> Result<()>,
) -> std::result::Result<Result<()>, usize> {
    if el.props.is_empty() {
        return Ok(Ok(()));
    }
    for row in 0..el.count {
        for (pi, p) in el.props.iter().enumerate() {
            match p.ty {
                PropType::Scalar(s) => {
                    let v = body.next(s).ok_or(row)?;
                    if let Err(e) = f(row, (pi, v)) {
                        return Ok(Err(e));
                    }
                }
                PropType::List { count, item } => {
                    let len = body.next(count).ok_or(row)?;
                    if len < 0.0 {
                        return Err(row);
                    }
                    for _ in 0..len as u64 {
                        body.next(item).ok_or(row)?;
                    }
                }
            }
        }
    }
    Ok(Ok(()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;
    use proptest::prelude::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn random_set(n: usize, degree: u32, seed: u64) -> GaussianSet {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut set = GaussianSet::new(degree);
        let rest_w = set.width(ParamGroup::ShRest);
        for _ in 0..n {
            let mut r = || rng.random_range(-2.0f32..2.0);
            let rest: Vec<f32> = (0..rest_w).map(|_| r()).collect();
            set.push(
                Vec3::new(r(), r(), r()),
                Vec3::new(r(), r(), r()),
                [r(), r(), r(), r()],
                r(),
                [r(), r(), r()],
                &rest,
            );
        }
        set
    }

    fn p() -> &'static Path {
        Path::new("test.ply")
    }

    fn message(e: Error) -> String {
        match e {
            Error::File(crate::error::FileError::BadFile { path, message }) => {
                assert_eq!(path, p());
                message
            }
            other => panic!("expected BadFile, got {other:?}"),
        }
    }

    #[test]
    fn round_trip_is_exact_for_every_degree() {
        for degree in 0..=3 {
            let set = random_set(37, degree, degree as u64);
            let back = decode_ply(&encode_ply(&set), p()).unwrap();
            assert_eq!(back, set, "degree {degree}");
        }
        let empty = GaussianSet::new(3);
        assert_eq!(decode_ply(&encode_ply(&empty), p()).unwrap(), empty);
    }

    #[test]
    fn file_round_trip() {
        let dir = std::env::temp_dir().join(format!("aim-ply-unit-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("set.ply");
        let set = random_set(10, 1, 7);
        write_ply(&path, &set).unwrap();
        assert_eq!(read_ply(&path).unwrap(), set);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn f_rest_is_channel_major_in_the_file() {
        let mut set = GaussianSet::new(1);
        // Coefficient-major [k][c]: value 10*k + c.
        let rest: Vec<f32> = (0..3).flat_map(|k| (0..3).map(move |c| (10 * k + c) as f32)).collect();
        set.push(Vec3::ZERO, Vec3::ZERO, [1.0, 0.0, 0.0, 0.0], 0.0, [0.0; 3], &rest);
        let bytes = encode_ply(&set);
        let h = parse_header(&bytes, p()).unwrap();
        let names: Vec<&str> = h.elements[0].props.iter().map(|p| p.name.as_str()).collect();
        assert_eq!(names, property_names(1).iter().map(String::as_str).collect::<Vec<_>>());
        let vals: Vec<f32> =
            bytes[h.body_start..].chunks(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect();
        // f_rest_0..8 follow x y z nx ny nz f_dc_0..2; channel-major: c*3 + k.
        assert_eq!(&vals[9..18], &[0.0, 10.0, 20.0, 1.0, 11.0, 21.0, 2.0, 12.0, 22.0]);
    }

    /// An ascii file with reordered properties, doubles, extra properties and elements.
    #[test]
    fn reads_ascii_reordered_with_extras() {
        let text = "ply\r\nformat ascii 1.0\r\ncomment made by hand\r\nelement camera 1\r\nproperty list uchar int ids\r\n\
            property float fov\r\nelement vertex 2\r\nproperty double rot_3\r\nproperty float opacity\r\nproperty uchar red\r\n\
            property float rot_0\r\nproperty float rot_1\r\nproperty float rot_2\r\nproperty float scale_2\r\n\
            property float scale_1\r\nproperty float scale_0\r\nproperty float f_dc_0\r\nproperty float f_dc_1\r\n\
            property float f_dc_2\r\nproperty float z\r\nproperty float y\r\nproperty float x\r\nend_header\r\n\
            3 1 2 3 0.5\r\n\
            4 0.5 255 1 2 3 -1 -2 -3 0.1 0.2 0.3 7 8 9\r\n\
            -4 -0.5 0 -1 -2 -3 1 2 3 -0.1 -0.2 -0.3 -7 -8 -9\r\n";
        let set = decode_ply(text.as_bytes(), p()).unwrap();
        assert_eq!(set.sh_degree, 0);
        assert_eq!(set.means, vec![9.0, 8.0, 7.0, -9.0, -8.0, -7.0]);
        assert_eq!(set.rotations, vec![1.0, 2.0, 3.0, 4.0, -1.0, -2.0, -3.0, -4.0]);
        assert_eq!(set.log_scales, vec![-3.0, -2.0, -1.0, 3.0, 2.0, 1.0]);
        assert_eq!(set.opacity_logits, vec![0.5, -0.5]);
        assert_eq!(set.sh_dc, vec![0.1, 0.2, 0.3, -0.1, -0.2, -0.3]);
    }

    #[test]
    fn reads_big_endian() {
        let set = random_set(3, 0, 3);
        let le = encode_ply(&set);
        let h = parse_header(&le, p()).unwrap();
        let header = String::from_utf8(le[..h.body_start].to_vec()).unwrap().replace("little", "big");
        let mut be = header.into_bytes();
        for c in le[h.body_start..].chunks(4) {
            be.extend(c.iter().rev());
        }
        assert_eq!(decode_ply(&be, p()).unwrap(), set);
    }

    fn header_with(props: &[(&str, &str)], count: usize) -> String {
        let mut s = format!("ply\nformat binary_little_endian 1.0\nelement vertex {count}\n");
        for (ty, name) in props {
            s += &format!("property {ty} {name}\n");
        }
        s + "end_header\n"
    }

    fn standard_props() -> Vec<(&'static str, String)> {
        property_names(0).into_iter().map(|n| ("float", n)).collect()
    }

    #[test]
    fn rejects_missing_properties() {
        let props: Vec<(&str, String)> = standard_props().into_iter().filter(|(_, n)| n != "rot_2").collect();
        let props: Vec<(&str, &str)> = props.iter().map(|(t, n)| (*t, n.as_str())).collect();
        let msg = message(decode_ply(header_with(&props, 0).as_bytes(), p()).unwrap_err());
        assert!(msg.contains("lacks") && msg.contains("rot_2"), "{msg}");
    }

    #[test]
    fn rejects_wrong_types_and_bad_rest_counts() {
        let mut props = standard_props();
        props[0].0 = "int";
        let props: Vec<(&str, &str)> = props.iter().map(|(t, n)| (*t, n.as_str())).collect();
        let msg = message(decode_ply(header_with(&props, 0).as_bytes(), p()).unwrap_err());
        assert!(msg.contains("'x'") && msg.contains("type int"), "{msg}");

        let mut props: Vec<(&str, String)> = standard_props();
        props.extend((0..5).map(|i| ("float", format!("f_rest_{i}"))));
        let props: Vec<(&str, &str)> = props.iter().map(|(t, n)| (*t, n.as_str())).collect();
        let msg = message(decode_ply(header_with(&props, 0).as_bytes(), p()).unwrap_err());
        assert!(msg.contains("5 f_rest"), "{msg}");
    }

    #[test]
    fn rejects_non_finite_values_naming_property_and_vertex() {
        let mut set = random_set(4, 0, 1);
        set.log_scales[2 * 3 + 1] = f32::NAN;
        let msg = message(decode_ply(&encode_ply(&set), p()).unwrap_err());
        assert!(msg.contains("vertex 2") && msg.contains("scale_1"), "{msg}");
        set.log_scales[2 * 3 + 1] = 0.0;
        set.opacity_logits[3] = f32::INFINITY;
        let msg = message(decode_ply(&encode_ply(&set), p()).unwrap_err());
        assert!(msg.contains("vertex 3") && msg.contains("opacity"), "{msg}");
    }

    #[test]
    fn rejects_truncated_body_and_bad_headers() {
        let bytes = encode_ply(&random_set(5, 1, 2));
        let msg = message(decode_ply(&bytes[..bytes.len() - 3], p()).unwrap_err());
        assert!(msg.contains("truncated"), "{msg}");
        let msg = message(decode_ply(b"PLY\nformat ascii 1.0\nend_header\n", p()).unwrap_err());
        assert!(msg.contains("magic"), "{msg}");
        let msg = message(decode_ply(b"ply\nformat ascii 1.0\nelement vertex 1\n", p()).unwrap_err());
        assert!(msg.contains("end_header"), "{msg}");
        let msg = message(decode_ply(b"ply\nformat ascii 1.0\nelement face 0\nend_header\n", p()).unwrap_err());
        assert!(msg.contains("no 'vertex'"), "{msg}");
        let huge = header_with(&standard_props().iter().map(|(t, n)| (*t, n.as_str())).collect::<Vec<_>>(), usize::MAX);
        let msg = message(decode_ply(huge.as_bytes(), p()).unwrap_err());
        assert!(msg.contains("truncated"), "{msg}");
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(512))]

        /// Any mutation or truncation of a valid file decodes or fails cleanly.
        #[test]
        fn mutated_bytes_never_panic(
            degree in 0u32..=3,
            edits in proptest::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 0..8),
            cut in any::<prop::sample::Index>(),
            ascii in any::<bool>(),
        ) {
            let set = random_set(3, degree, 11);
            let mut bytes = if ascii {
                let h = parse_header(&encode_ply(&set), p()).unwrap();
                let header = h.elements[0].props.iter().fold(
                    format!("ply\nformat ascii 1.0\nelement vertex {}\n", set.len()),
                    |s, pr| s + &format!("property float {}\n", pr.name),
                ) + "end_header\n";
                let body: String = (0..set.len()).map(|_| "0.5 ".repeat(h.elements[0].props.len()) + "\n").collect();
                (header + &body).into_bytes()
            } else {
                encode_ply(&set)
            };
            for (i, b) in edits {
                let i = i.index(bytes.len());
                bytes[i] = b;
            }
            let end = cut.index(bytes.len() + 1);
            let _ = decode_ply(&bytes[..end], p());
            let _ = decode_point_cloud(&bytes[..end], p());
        }

        #[test]
        fn random_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..512)) {
            let mut with_magic = b"ply\nformat binary_little_endian 1.0\n".to_vec();
            with_magic.extend_from_slice(&bytes);
            let _ = decode_ply(&bytes, p());
            let _ = decode_ply(&with_magic, p());
        }
    }
}
