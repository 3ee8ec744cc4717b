//! COLMAP sparse models: `cameras`, `images`, `points3D` as `.bin` or `.txt`.
//!
//! COLMAP poses are already OpenCV world-to-camera (`qvec` w, x, y, z and `tvec`), and
//! COLMAP puts pixel centres at (i + 0.5, j + 0.5) like this library, so intrinsics
//! carry over unchanged. Distortion parameters are kept in [`ColmapCamera::params`];
//! [`load_colmap_frames`] gives pinhole intrinsics (fx, fy, cx, cy) and leaves
//! undistortion to the caller ([`ColmapCamera::is_pinhole`] says when none is needed).
//!
//! Parsers check every count against the bytes left, so corrupt files are errors
//! naming the file and the offset or line, never a panic or a huge allocation.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use glam::{DMat3, DQuat, DVec3, Mat4, Vec3};
use rayon::prelude::*;

use super::{read_rgba, LoadOptions, NOMINAL_FPS};
use crate::error::{Error, Result};
use crate::frame::{Frame, Intrinsics, Phase};

/// COLMAP camera models: (id, name, number of parameters).
pub const CAMERA_MODELS: [(i32, &str, usize); 11] = [
    (0, "SIMPLE_PINHOLE", 3),
    (1, "PINHOLE", 4),
    (2, "SIMPLE_RADIAL", 4),
    (3, "RADIAL", 5),
    (4, "OPENCV", 8),
    (5, "OPENCV_FISHEYE", 8),
    (6, "FULL_OPENCV", 12),
    (7, "FOV", 5),
    (8, "SIMPLE_RADIAL_FISHEYE", 4),
    (9, "RADIAL_FISHEYE", 5),
    (10, "THIN_PRISM_FISHEYE", 12),
];

#[derive(Clone, Debug, PartialEq)]
pub struct ColmapCamera {
    pub id: u32,
    pub model: String,
    pub width: u32,
    pub height: u32,
    pub params: Vec<f64>,
}

impl ColmapCamera {
    /// Focal lengths and principal point (models with one focal length repeat it).
    pub fn intrinsics(&self) -> Intrinsics {
        let p = &self.params;
        let (fx, fy, cx, cy) = match self.model.as_str() {
            "SIMPLE_PINHOLE" | "SIMPLE_RADIAL" | "RADIAL" | "SIMPLE_RADIAL_FISHEYE" | "RADIAL_FISHEYE" => {
                (p[0], p[0], p[1], p[2])
            }
            _ => (p[0], p[1], p[2], p[3]),
        };
        Intrinsics {
            width: self.width,
            height: self.height,
            fx: fx as f32,
            fy: fy as f32,
            cx: cx as f32,
            cy: cy as f32,
        }
    }

    /// True when the model has no distortion (or all its distortion terms are zero).
    pub fn is_pinhole(&self) -> bool {
        let skip = match self.model.as_str() {
            "SIMPLE_PINHOLE" | "PINHOLE" => return true,
            "SIMPLE_RADIAL" | "RADIAL" => 3,
            _ => 4,
        };
        self.params.iter().skip(skip).all(|&v| v == 0.0) && !self.model.contains("FISHEYE") && self.model != "FOV"
    }
}

#[derive(Clone, Debug, PartialEq)]
pub struct ColmapImage {
    pub id: u32,
    /// World-to-camera rotation, w x y z.
    pub qvec: [f64; 4],
    pub tvec: [f64; 3],
    pub camera_id: u32,
    pub name: String,
    /// Observations: (x, y, point3D id or -1).
    pub points2d: Vec<(f64, f64, i64)>,
}

impl ColmapImage {
    /// OpenCV world-to-camera.
    pub fn world_to_camera(&self) -> Mat4 {
        let [w, x, y, z] = self.qvec;
        let r = DMat3::from_quat(DQuat::from_xyzw(x, y, z, w).normalize());
        let t = DVec3::from(self.tvec);
        Mat4::from_cols(
            r.x_axis.as_vec3().extend(0.0),
            r.y_axis.as_vec3().extend(0.0),
            r.z_axis.as_vec3().extend(0.0),
            t.as_vec3().extend(1.0),
        )
    }
}

#[derive(Clone, Debug, PartialEq)]
pub struct ColmapPoint {
    pub id: u64,
    pub xyz: [f64; 3],
    pub rgb: [u8; 3],
    pub error: f64,
    /// (image id, point2D index).
    pub track: Vec<(u32, u32)>,
}

/// A sparse model. Images are sorted by name.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ColmapModel {
    pub cameras: BTreeMap<u32, ColmapCamera>,
    pub images: Vec<ColmapImage>,
    pub points: Vec<ColmapPoint>,
}

impl ColmapModel {
    /// Point positions (f32).
    pub fn point_positions(&self) -> Vec<Vec3> {
        self.points.iter().map(|p| DVec3::from(p.xyz).as_vec3()).collect()
    }
}

fn model_by_name(name: &str) -> Option<(i32, usize)> {
    CAMERA_MODELS.iter().find(|m| m.1 == name).map(|m| (m.0, m.2))
}

fn model_by_id(id: i32) -> Option<(&'static str, usize)> {
    CAMERA_MODELS.iter().find(|m| m.0 == id).map(|m| (m.1, m.2))
}

fn check_camera(c: &ColmapCamera, path: &Path) -> Result<()> {
    let k = c.intrinsics();
    if c.width == 0 || c.height == 0 || !(k.fx > 0.0 && k.fy > 0.0 && k.fx.is_finite() && k.fy.is_finite()) {
        return Err(Error::bad_file(path, format!("camera {}: size and focal lengths must be positive", c.id)));
    }
    if c.params.iter().any(|p| !p.is_finite()) {
        return Err(Error::bad_file(path, format!("camera {}: non-finite parameter", c.id)));
    }
    Ok(())
}

// ------------------------------------------------------------------ text

fn parse_fields<T: std::str::FromStr>(fields: &[&str], path: &Path, line: usize, what: &str) -> Result<Vec<T>> {
    fields
        .iter()
        .map(|s| s.parse::<T>().map_err(|_| Error::bad_file(path, format!("line {line}: bad {what} value {s:?}"))))
        .collect()
}

fn content_lines(text: &str) -> impl Iterator<Item = (usize, &str)> {
    text.lines().enumerate().map(|(i, l)| (i + 1, l.trim())).filter(|(_, l)| !l.starts_with('#'))
}

fn read_text(path: &Path) -> Result<String> {
    std::fs::read_to_string(path).map_err(|e| Error::io(path, e))
}

fn read_cameras_txt(path: &Path) -> Result<BTreeMap<u32, ColmapCamera>> {
    let text = read_text(path)?;
    let mut out = BTreeMap::new();
    for (ln, line) in content_lines(&text).filter(|(_, l)| !l.is_empty()) {
        let f: Vec<&str> = line.split_whitespace().collect();
        if f.len() < 4 {
            return Err(Error::bad_file(path, format!("line {ln}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS...")));
        }
        let (_, n) = model_by_name(f[1])
            .ok_or_else(|| Error::bad_file(path, format!("line {ln}: unknown camera model {:?}", f[1])))?;
        if f.len() != 4 + n {
            return Err(Error::bad_file(
                path,
                format!("line {ln}: {} needs {n} parameters, found {}", f[1], f.len() - 4),
            ));
        }
        let ids: Vec<u32> = parse_fields(&[f[0], f[2], f[3]], path, ln, "integer")?;
        let cam = ColmapCamera {
            id: ids[0],
            model: f[1].to_string(),
            width: ids[1],
            height: ids[2],
            params: parse_fields(&f[4..], path, ln, "parameter")?,
        };
        check_camera(&cam, path)?;
        out.insert(cam.id, cam);
    }
    Ok(out)
}

fn read_images_txt(path: &Path) -> Result<Vec<ColmapImage>> {
    let text = read_text(path)?;
    let mut out = Vec::new();
    let mut lines = content_lines(&text);
    while let Some((ln, line)) = lines.next() {
        if line.is_empty() {
            continue;
        }
        let f: Vec<&str> = line.split_whitespace().collect();
        if f.len() < 10 {
            return Err(Error::bad_file(
                path,
                format!("line {ln}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME"),
            ));
        }
        let v: Vec<f64> = parse_fields(&f[1..8], path, ln, "pose")?;
        let ids: Vec<u32> = parse_fields(&[f[0], f[8]], path, ln, "id")?;
        // The name may contain spaces: everything after the camera id.
        let name = f[9..].join(" ");
        let mut points2d = Vec::new();
        if let Some((ln2, pl)) = lines.next() {
            let p: Vec<&str> = pl.split_whitespace().collect();
            if !p.len().is_multiple_of(3) {
                return Err(Error::bad_file(path, format!("line {ln2}: POINTS2D must be triples X Y POINT3D_ID")));
            }
            for c in p.chunks(3) {
                let xy: Vec<f64> = parse_fields(&c[..2], path, ln2, "point")?;
                let id: Vec<i64> = parse_fields(&c[2..], path, ln2, "point3D id")?;
                points2d.push((xy[0], xy[1], id[0]));
            }
        }
        let img = ColmapImage {
            id: ids[0],
            qvec: [v[0], v[1], v[2], v[3]],
            tvec: [v[4], v[5], v[6]],
            camera_id: ids[1],
            name,
            points2d,
        };
        check_image(&img, path)?;
        out.push(img);
    }
    Ok(out)
}

fn check_image(img: &ColmapImage, path: &Path) -> Result<()> {
    let qn = img.qvec.iter().map(|q| q * q).sum::<f64>().sqrt();
    if !qn.is_finite() || qn < 1e-6 || img.tvec.iter().any(|t| !t.is_finite()) {
        return Err(Error::bad_file(path, format!("image {} ({}): invalid pose", img.id, img.name)));
    }
    Ok(())
}

fn read_points_txt(path: &Path) -> Result<Vec<ColmapPoint>> {
    let text = read_text(path)?;
    let mut out = Vec::new();
    for (ln, line) in content_lines(&text).filter(|(_, l)| !l.is_empty()) {
        let f: Vec<&str> = line.split_whitespace().collect();
        if f.len() < 8 || !(f.len() - 8).is_multiple_of(2) {
            return Err(Error::bad_file(path, format!("line {ln}: expected POINT3D_ID X Y Z R G B ERROR TRACK[]")));
        }
        let id: Vec<u64> = parse_fields(&f[..1], path, ln, "id")?;
        let xyz: Vec<f64> = parse_fields(&f[1..4], path, ln, "coordinate")?;
        let rgb: Vec<u8> = parse_fields(&f[4..7], path, ln, "colour")?;
        let err: Vec<f64> = parse_fields(&f[7..8], path, ln, "error")?;
        let tr: Vec<u32> = parse_fields(&f[8..], path, ln, "track")?;
        out.push(ColmapPoint {
            id: id[0],
            xyz: [xyz[0], xyz[1], xyz[2]],
            rgb: [rgb[0], rgb[1], rgb[2]],
            error: err[0],
            track: tr.chunks(2).map(|c| (c[0], c[1])).collect(),
        });
    }
    Ok(out)
}

// ------------------------------------------------------------------ binary

struct Reader<'a> {
    bytes: &'a [u8],
    pos: usize,
    path: &'a Path,
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize) -> Result<&'a [u8]> {
        if self.bytes.len() - self.pos < n {
            return Err(Error::bad_file(
                self.path,
                format!("truncated: needed {n} bytes at offset {}, file has {}", self.pos, self.bytes.len()),
            ));
        }
        let s = &self.bytes[self.pos..self.pos + n];
        self.pos += n;
        Ok(s)
    }
    fn arr<const N: usize>(&mut self) -> Result<[u8; N]> {
        let mut a = [0u8; N];
        a.copy_from_slice(self.take(N)?);
        Ok(a)
    }
    fn u64(&mut self) -> Result<u64> {
        Ok(u64::from_le_bytes(self.arr()?))
    }
    fn i64(&mut self) -> Result<i64> {
        Ok(i64::from_le_bytes(self.arr()?))
    }
    fn i32(&mut self) -> Result<i32> {
        Ok(i32::from_le_bytes(self.arr()?))
    }
    fn u32(&mut self) -> Result<u32> {
        Ok(u32::from_le_bytes(self.arr()?))
    }
    fn f64(&mut self) -> Result<f64> {
        Ok(f64::from_le_bytes(self.arr()?))
    }
    fn u8(&mut self) -> Result<u8> {
        Ok(self.take(1)?[0])
    }
    /// A count of records of at least `min_size` bytes each, checked against what is left.
    fn count(&mut self, min_size: usize, what: &str) -> Result<usize> {
        let at = self.pos;
        let n = self.u64()?;
        let left = (self.bytes.len() - self.pos) as u64;
        if n > left / min_size.max(1) as u64 {
            return Err(Error::bad_file(
                self.path,
                format!("offset {at}: {n} {what} cannot fit in the {left} bytes left"),
            ));
        }
        Ok(n as usize)
    }
    fn id_u32(&mut self, what: &str) -> Result<u32> {
        let at = self.pos;
        let v = self.i32()?;
        u32::try_from(v).map_err(|_| Error::bad_file(self.path, format!("offset {at}: negative {what} {v}")))
    }
    fn end(&self) -> Result<()> {
        if self.pos != self.bytes.len() {
            return Err(Error::bad_file(
                self.path,
                format!("{} unexpected bytes after offset {}", self.bytes.len() - self.pos, self.pos),
            ));
        }
        Ok(())
    }
}

fn read_bytes(path: &Path) -> Result<Vec<u8>> {
    std::fs::read(path).map_err(|e| Error::io(path, e))
}

/// Parse cameras.bin content (`path` names it in errors).
pub fn parse_cameras_bin(bytes: &[u8], path: &Path) -> Result<BTreeMap<u32, ColmapCamera>> {
    let mut r = Reader { bytes, pos: 0, path };
    let n = r.count(24, "cameras")?;
    let mut out = BTreeMap::new();
    for _ in 0..n {
        let id = r.id_u32("camera id")?;
        let at = r.pos;
        let model_id = r.i32()?;
        let (name, np) = model_by_id(model_id)
            .ok_or_else(|| Error::bad_file(path, format!("offset {at}: unknown camera model id {model_id}")))?;
        let (w, h) = (r.u64()?, r.u64()?);
        let params = (0..np).map(|_| r.f64()).collect::<Result<Vec<_>>>()?;
        let cam = ColmapCamera {
            id,
            model: name.to_string(),
            width: u32::try_from(w).map_err(|_| Error::bad_file(path, format!("camera {id}: width {w} too large")))?,
            height: u32::try_from(h)
                .map_err(|_| Error::bad_file(path, format!("camera {id}: height {h} too large")))?,
            params,
        };
        check_camera(&cam, path)?;
        out.insert(id, cam);
    }
    r.end()?;
    Ok(out)
}

/// Parse images.bin content.
pub fn parse_images_bin(bytes: &[u8], path: &Path) -> Result<Vec<ColmapImage>> {
    let mut r = Reader { bytes, pos: 0, path };
    let n = r.count(4 + 56 + 4 + 1 + 8, "images")?;
    let mut out = Vec::with_capacity(n);
    for _ in 0..n {
        let id = r.id_u32("image id")?;
        let q = [r.f64()?, r.f64()?, r.f64()?, r.f64()?];
        let t = [r.f64()?, r.f64()?, r.f64()?];
        let camera_id = r.id_u32("camera id")?;
        let at = r.pos;
        let rest = &bytes[r.pos..];
        let len = rest
            .iter()
            .position(|&b| b == 0)
            .ok_or_else(|| Error::bad_file(path, format!("offset {at}: unterminated image name")))?;
        let name = String::from_utf8(r.take(len)?.to_vec())
            .map_err(|_| Error::bad_file(path, format!("offset {at}: image name is not UTF-8")))?;
        r.take(1)?;
        let np = r.count(24, "2D points")?;
        let mut points2d = Vec::with_capacity(np);
        for _ in 0..np {
            points2d.push((r.f64()?, r.f64()?, r.i64()?));
        }
        let img = ColmapImage { id, qvec: q, tvec: t, camera_id, name, points2d };
        check_image(&img, path)?;
        out.push(img);
    }
    r.end()?;
    Ok(out)
}

/// Parse points3D.bin content.
pub fn parse_points_bin(bytes: &[u8], path: &Path) -> Result<Vec<ColmapPoint>> {
    let mut r = Reader { bytes, pos: 0, path };
    let n = r.count(8 + 24 + 3 + 8 + 8, "points")?;
    let mut out = Vec::with_capacity(n);
    for _ in 0..n {
        let id = r.u64()?;
        let xyz = [r.f64()?, r.f64()?, r.f64()?];
        let rgb = [r.u8()?, r.u8()?, r.u8()?];
        let error = r.f64()?;
        let tl = r.count(8, "track elements")?;
        let mut track = Vec::with_capacity(tl);
        for _ in 0..tl {
            track.push((r.u32()?, r.u32()?));
        }
        out.push(ColmapPoint { id, xyz, rgb, error, track });
    }
    r.end()?;
    Ok(out)
}

/// Find `name.bin` or `name.txt` in `dir` (binary preferred).
fn find(dir: &Path, name: &str) -> Result<(PathBuf, bool)> {
    let bin = dir.join(format!("{name}.bin"));
    if bin.is_file() {
        return Ok((bin, true));
    }
    let txt = dir.join(format!("{name}.txt"));
    if txt.is_file() {
        return Ok((txt, false));
    }
    Err(Error::bad_file(
        dir.join(format!("{name}.bin")),
        format!("missing: neither {name}.bin nor {name}.txt in this folder"),
    ))
}

/// Read a sparse model folder (e.g. `sparse/0`). points3D is optional.
pub fn read_colmap_model(dir: &Path) -> Result<ColmapModel> {
    let (cp, cbin) = find(dir, "cameras")?;
    let cameras = if cbin { parse_cameras_bin(&read_bytes(&cp)?, &cp)? } else { read_cameras_txt(&cp)? };
    let (ip, ibin) = find(dir, "images")?;
    let mut images = if ibin { parse_images_bin(&read_bytes(&ip)?, &ip)? } else { read_images_txt(&ip)? };
    for img in &images {
        if !cameras.contains_key(&img.camera_id) {
            return Err(Error::bad_file(
                &ip,
                format!("image {} ({}) uses unknown camera {}", img.id, img.name, img.camera_id),
            ));
        }
    }
    images.sort_by(|a, b| a.name.cmp(&b.name));
    let points = match find(dir, "points3D") {
        Ok((pp, true)) => parse_points_bin(&read_bytes(&pp)?, &pp)?,
        Ok((pp, false)) => read_points_txt(&pp)?,
        Err(_) => Vec::new(),
    };
    Ok(ColmapModel { cameras, images, points })
}

/// Frames for every registered image of a model, images read from `images_dir`, in name order.
/// Returns the model too (for distortion parameters and points).
pub fn load_colmap_frames(
    model_dir: &Path,
    images_dir: &Path,
    _opts: &LoadOptions,
) -> Result<(ColmapModel, Vec<Frame>)> {
    let model = read_colmap_model(model_dir)?;
    let frames = model
        .images
        .par_iter()
        .enumerate()
        .map(|(index, img)| {
            let cam = &model.cameras[&img.camera_id];
            let path = images_dir.join(&img.name);
            let image = read_rgba(&path)?;
            let mut k = cam.intrinsics();
            if (image.width(), image.height()) != (cam.width, cam.height) {
                // Downscaled image folders (images_2, ...): rescale the intrinsics.
                k = k.scaled(image.width(), image.height());
            }
            Ok(Frame {
                index,
                timestamp_s: index as f64 / NOMINAL_FPS,
                motion_time: None,
                phase: Phase::Scan,
                intrinsics: k,
                world_to_camera: img.world_to_camera(),
                image: Arc::new(image),
                depth: None,
                source: path.display().to_string(),
            })
        })
        .collect::<Result<Vec<_>>>()?;
    Ok((model, frames))
}

// ------------------------------------------------------------------ writing

/// Write the model as cameras.txt, images.txt and points3D.txt into `dir`.
pub fn write_colmap_text(model: &ColmapModel, dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    let mut s = String::from(
        "# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n",
    );
    for c in model.cameras.values() {
        let _ = write!(s, "{} {} {} {}", c.id, c.model, c.width, c.height);
        for p in &c.params {
            let _ = write!(s, " {p:?}");
        }
        s.push('\n');
    }
    crate::io::write_atomic(&dir.join("cameras.txt"), s.as_bytes())?;
    let mut s = String::from("# Image list with two lines of data per image:\n#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n#   POINTS2D[] as (X, Y, POINT3D_ID)\n");
    for i in &model.images {
        let [qw, qx, qy, qz] = i.qvec;
        let [tx, ty, tz] = i.tvec;
        let _ = writeln!(s, "{} {qw:?} {qx:?} {qy:?} {qz:?} {tx:?} {ty:?} {tz:?} {} {}", i.id, i.camera_id, i.name);
        let pts: Vec<String> = i.points2d.iter().map(|(x, y, id)| format!("{x:?} {y:?} {id}")).collect();
        let _ = writeln!(s, "{}", pts.join(" "));
    }
    crate::io::write_atomic(&dir.join("images.txt"), s.as_bytes())?;
    let mut s = String::from("# 3D point list with one line of data per point:\n#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n");
    for p in &model.points {
        let _ = write!(
            s,
            "{} {:?} {:?} {:?} {} {} {} {:?}",
            p.id, p.xyz[0], p.xyz[1], p.xyz[2], p.rgb[0], p.rgb[1], p.rgb[2], p.error
        );
        for (a, b) in &p.track {
            let _ = write!(s, " {a} {b}");
        }
        s.push('\n');
    }
    crate::io::write_atomic(&dir.join("points3D.txt"), s.as_bytes())
}

/// Write the model as cameras.bin, images.bin and points3D.bin into `dir`.
pub fn write_colmap_bin(model: &ColmapModel, dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    let mut b = Vec::new();
    b.extend((model.cameras.len() as u64).to_le_bytes());
    for c in model.cameras.values() {
        let (id, _) = model_by_name(&c.model)
            .ok_or_else(|| Error::Other(format!("camera {}: unknown model {}", c.id, c.model)))?;
        b.extend((c.id as i32).to_le_bytes());
        b.extend(id.to_le_bytes());
        b.extend((c.width as u64).to_le_bytes());
        b.extend((c.height as u64).to_le_bytes());
        for p in &c.params {
            b.extend(p.to_le_bytes());
        }
    }
    crate::io::write_atomic(&dir.join("cameras.bin"), &b)?;
    let mut b = Vec::new();
    b.extend((model.images.len() as u64).to_le_bytes());
    for i in &model.images {
        b.extend((i.id as i32).to_le_bytes());
        for v in i.qvec.iter().chain(&i.tvec) {
            b.extend(v.to_le_bytes());
        }
        b.extend((i.camera_id as i32).to_le_bytes());
        b.extend(i.name.as_bytes());
        b.push(0);
        b.extend((i.points2d.len() as u64).to_le_bytes());
        for (x, y, id) in &i.points2d {
            b.extend(x.to_le_bytes());
            b.extend(y.to_le_bytes());
            b.extend(id.to_le_bytes());
        }
    }
    crate::io::write_atomic(&dir.join("images.bin"), &b)?;
    let mut b = Vec::new();
    b.extend((model.points.len() as u64).to_le_bytes());
    for p in &model.points {
        b.extend(p.id.to_le_bytes());
        for v in p.xyz {
            b.extend(v.to_le_bytes());
        }
        b.extend(p.rgb);
        b.extend(p.error.to_le_bytes());
        b.extend((p.track.len() as u64).to_le_bytes());
        for (a, c) in &p.track {
            b.extend(a.to_le_bytes());
            b.extend(c.to_le_bytes());
        }
    }
    crate::io::write_atomic(&dir.join("points3D.bin"), &b)
}

/// COLMAP image entry for an OpenCV world-to-camera pose.
pub fn image_from_pose(id: u32, camera_id: u32, name: &str, world_to_camera: &Mat4) -> ColmapImage {
    let r = glam::Mat3::from_mat4(*world_to_camera).as_dmat3();
    let q = DQuat::from_mat3(&r).normalize();
    let t = world_to_camera.w_axis.truncate().as_dvec3();
    ColmapImage {
        id,
        qvec: [q.w, q.x, q.y, q.z],
        tvec: t.to_array(),
        camera_id,
        name: name.to_string(),
        points2d: Vec::new(),
    }
}
