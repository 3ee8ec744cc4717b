//! Triangle meshes: the ground-truth part meshes, the meshes extracted from
//! trained Gaussians ([`tsdf`]), and what the metrics and exports need of them
//! (area-uniform surface samples, connected components, OBJ and PLY files).

use std::path::Path;

use glam::{Affine3A, Vec3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

use crate::error::{write_atomic, Error, Result};

pub(crate) mod inside;
pub mod tsdf;

use inside::ComponentSolids;

/// An indexed triangle mesh.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct MeshData {
    pub vertices: Vec<Vec3>,
    pub triangles: Vec<[u32; 3]>,
}

impl MeshData {
    pub fn is_empty(&self) -> bool {
        self.triangles.is_empty()
    }

    pub fn transformed(&self, m: &Affine3A) -> Self {
        Self {
            vertices: self.vertices.iter().map(|&v| m.transform_point3(v)).collect(),
            triangles: self.triangles.clone(),
        }
    }

    /// All of `meshes` in one (vertex indices renumbered).
    pub fn merged<'a>(meshes: impl IntoIterator<Item = &'a MeshData>) -> Self {
        let mut out = MeshData::default();
        for m in meshes {
            let base = out.vertices.len() as u32;
            out.vertices.extend_from_slice(&m.vertices);
            out.triangles.extend(m.triangles.iter().map(|t| t.map(|i| i + base)));
        }
        out
    }

    fn corners(&self, t: &[u32; 3]) -> [Vec3; 3] {
        t.map(|i| self.vertices[i as usize])
    }

    fn triangle_area(&self, t: &[u32; 3]) -> f32 {
        let [a, b, c] = self.corners(t);
        0.5 * (b - a).cross(c - a).length()
    }

    /// Total surface area.
    pub fn area(&self) -> f32 {
        self.triangles.iter().map(|t| self.triangle_area(t)).sum()
    }

    /// Axis-aligned bounds (min, max) of the vertices the triangles use; None if empty.
    pub fn bounds(&self) -> Option<(Vec3, Vec3)> {
        let mut it = self.triangles.iter().flatten().map(|&i| self.vertices[i as usize]);
        let first = it.next()?;
        Some(it.fold((first, first), |(lo, hi), v| (lo.min(v), hi.max(v))))
    }

    /// `n` points uniformly distributed over the surface (area-weighted triangle
    /// choice, uniform barycentric coordinates), from a seeded stream.
    pub fn sample_surface(&self, n: usize, seed: u64) -> Vec<Vec3> {
        self.sample_surface_with(n, &mut ChaCha8Rng::seed_from_u64(seed))
    }

    /// As [`Self::sample_surface`], drawing from `rng`.
    pub fn sample_surface_with(&self, n: usize, rng: &mut impl Rng) -> Vec<Vec3> {
        self.sample_triangles(n, rng).into_iter().map(|(_, p)| p).collect()
    }

    /// `n` area-uniform samples, each with the triangle it lies on.
    fn sample_triangles(&self, n: usize, rng: &mut impl Rng) -> Vec<(usize, Vec3)> {
        let mut cumulative = Vec::with_capacity(self.triangles.len());
        let mut total = 0.0f32;
        for t in &self.triangles {
            total += self.triangle_area(t);
            cumulative.push(total);
        }
        if total <= 0.0 {
            return Vec::new();
        }
        (0..n)
            .map(|_| {
                let x = rng.random_range(0.0..total);
                let k = cumulative.partition_point(|&c| c < x).min(self.triangles.len() - 1);
                let [a, b, c] = self.corners(&self.triangles[k]);
                let (mut u, mut v): (f32, f32) = (rng.random(), rng.random());
                if u + v > 1.0 {
                    (u, v) = (1.0 - u, 1.0 - v);
                }
                (k, a + u * (b - a) + v * (c - a))
            })
            .collect()
    }

    /// `n` area-uniform samples of the surface that bounds the solid: samples
    /// inside (or on) another connected component are dropped and drawn again.
    /// A model built from overlapping closed primitives (the benchmark's: a
    /// door's bins pressed against its panel, a handle sunk into a door) has
    /// faces inside the solid that no camera can see. Components are taken as
    /// closed; inside means a generalized winding number above 1/4 (1 inside,
    /// 1/2 on the surface, 0 outside, whatever the triangles' orientation;
    /// [`inside`] says how large components are tested fast). Fewer than `n`
    /// samples only when the visible surface is a tiny fraction of the whole.
    pub fn sample_outer_surface(&self, n: usize, seed: u64) -> Vec<Vec3> {
        let solids = ComponentSolids::new(self);
        if solids.count() <= 1 {
            return self.sample_surface(n, seed);
        }
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut out = Vec::with_capacity(n);
        for _ in 0..20 {
            let batch = self.sample_triangles(2 * (n - out.len()), &mut rng);
            let keep: Vec<Vec3> = batch
                .par_iter()
                .filter(|(k, p)| !solids.inside_another(solids.component[*k] as usize, *p))
                .map(|(_, p)| *p)
                .collect();
            out.extend(keep.into_iter().take(n - out.len()));
            if out.len() == n {
                break;
            }
        }
        out
    }

    /// Generalized winding number of the triangles `tris` at `p` (solid angles
    /// over 4 pi, Van Oosterom and Strackee).
    fn winding_number(&self, tris: &[usize], p: Vec3) -> f32 {
        let total: f64 = tris
            .iter()
            .map(|&t| {
                let [a, b, c] = self.corners(&self.triangles[t]).map(|v| (v - p).as_dvec3());
                let (la, lb, lc) = (a.length(), b.length(), c.length());
                let det = a.dot(b.cross(c));
                let div = la * lb * lc + a.dot(b) * lc + b.dot(c) * la + c.dot(a) * lb;
                2.0 * det.atan2(div)
            })
            .sum();
        (total / (4.0 * std::f64::consts::PI)) as f32
    }

    /// The component of each triangle (triangles sharing a vertex index are
    /// connected) and the number of components.
    pub fn triangle_components(&self) -> (Vec<u32>, usize) {
        let mut parent: Vec<u32> = (0..self.vertices.len() as u32).collect();
        fn find(parent: &mut [u32], mut x: u32) -> u32 {
            while parent[x as usize] != x {
                parent[x as usize] = parent[parent[x as usize] as usize];
                x = parent[x as usize];
            }
            x
        }
        for t in &self.triangles {
            let r0 = find(&mut parent, t[0]);
            for &v in &t[1..] {
                let r = find(&mut parent, v);
                if r != r0 {
                    parent[r as usize] = r0;
                }
            }
        }
        let mut label = vec![u32::MAX; self.vertices.len()];
        let mut count = 0usize;
        let comps = self
            .triangles
            .iter()
            .map(|t| {
                let r = find(&mut parent, t[0]) as usize;
                if label[r] == u32::MAX {
                    label[r] = count as u32;
                    count += 1;
                }
                label[r]
            })
            .collect();
        (comps, count)
    }

    /// The connected component with the largest surface area, its unused vertices dropped.
    pub fn largest_component(&self) -> MeshData {
        let (comps, count) = self.triangle_components();
        if count <= 1 {
            return self.compacted(|_| true);
        }
        let mut area = vec![0.0f64; count];
        for (t, &c) in self.triangles.iter().zip(&comps) {
            area[c as usize] += f64::from(self.triangle_area(t));
        }
        let best = (0..count).max_by(|&a, &b| area[a].total_cmp(&area[b])).unwrap_or(0) as u32;
        self.compacted(|k| comps[k] == best)
    }

    /// The triangles `keep` accepts (by index), with only the vertices they use.
    fn compacted(&self, keep: impl Fn(usize) -> bool) -> MeshData {
        let mut remap = vec![u32::MAX; self.vertices.len()];
        let mut out = MeshData::default();
        for (k, t) in self.triangles.iter().enumerate() {
            if !keep(k) {
                continue;
            }
            out.triangles.push(t.map(|i| {
                if remap[i as usize] == u32::MAX {
                    remap[i as usize] = out.vertices.len() as u32;
                    out.vertices.push(self.vertices[i as usize]);
                }
                remap[i as usize]
            }));
        }
        out
    }

    /// Wavefront OBJ text (1-based indices).
    pub fn to_obj(&self, comment: &str) -> String {
        use std::fmt::Write;
        let mut s = String::with_capacity(self.vertices.len() * 40 + self.triangles.len() * 24);
        for line in comment.lines() {
            let _ = writeln!(s, "# {line}");
        }
        for v in &self.vertices {
            let _ = writeln!(s, "v {:.6} {:.6} {:.6}", v.x, v.y, v.z);
        }
        for t in &self.triangles {
            let _ = writeln!(s, "f {} {} {}", t[0] + 1, t[1] + 1, t[2] + 1);
        }
        s
    }

    /// Binary little-endian PLY with `vertex (x y z float)` and `face (vertex_indices list uchar int)`.
    pub fn to_ply(&self) -> Vec<u8> {
        let header = format!(
            "ply\nformat binary_little_endian 1.0\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\nelement face {}\nproperty list uchar int vertex_indices\nend_header\n",
            self.vertices.len(),
            self.triangles.len()
        );
        let mut out = header.into_bytes();
        for v in &self.vertices {
            for c in v.to_array() {
                out.extend_from_slice(&c.to_le_bytes());
            }
        }
        for t in &self.triangles {
            out.push(3);
            for i in t {
                out.extend_from_slice(&(*i as i32).to_le_bytes());
            }
        }
        out
    }

    /// Write `stem.obj` and `stem.ply` (atomically) for the mesh.
    pub fn write_obj_and_ply(&self, stem: &Path, comment: &str) -> Result<()> {
        write_atomic(&stem.with_extension("obj"), self.to_obj(comment).as_bytes())?;
        write_atomic(&stem.with_extension("ply"), &self.to_ply())
    }
}

/// Read a Wavefront OBJ (v and f lines; polygons fanned into triangles; other lines ignored).
pub fn read_obj(path: &Path) -> Result<MeshData> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    let mut m = MeshData::default();
    for (ln, line) in text.lines().enumerate() {
        let mut it = line.split_whitespace();
        match it.next() {
            Some("v") => {
                let v: Vec<f32> = it
                    .take(3)
                    .map(|s| s.parse::<f32>())
                    .collect::<std::result::Result<_, _>>()
                    .map_err(|e| Error::bad_file(path, format!("line {}: bad vertex: {e}", ln + 1)))?;
                if v.len() != 3 || v.iter().any(|c| !c.is_finite()) {
                    return Err(Error::bad_file(path, format!("line {}: vertex needs 3 finite coordinates", ln + 1)));
                }
                m.vertices.push(Vec3::new(v[0], v[1], v[2]));
            }
            Some("f") => {
                let idx: Vec<u32> = it
                    .map(|s| s.split('/').next().unwrap_or("").parse::<u32>())
                    .collect::<std::result::Result<_, _>>()
                    .map_err(|e| Error::bad_file(path, format!("line {}: bad face: {e}", ln + 1)))?;
                if idx.len() < 3 || idx.iter().any(|&i| i == 0 || i as usize > m.vertices.len()) {
                    return Err(Error::bad_file(path, format!("line {}: face index out of range", ln + 1)));
                }
                for k in 1..idx.len() - 1 {
                    m.triangles.push([idx[0] - 1, idx[k] - 1, idx[k + 1] - 1]);
                }
            }
            _ => {}
        }
    }
    Ok(m)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn two_triangles_apart() -> MeshData {
        MeshData {
            vertices: vec![
                Vec3::ZERO,
                Vec3::X,
                Vec3::Y,
                Vec3::new(5.0, 0.0, 0.0),
                Vec3::new(7.0, 0.0, 0.0),
                Vec3::new(5.0, 2.0, 0.0),
            ],
            triangles: vec![[0, 1, 2], [3, 4, 5]],
        }
    }

    #[test]
    fn components_and_the_largest_one() {
        let m = two_triangles_apart();
        let (comps, n) = m.triangle_components();
        assert_eq!(n, 2);
        assert_ne!(comps[0], comps[1]);
        let big = m.largest_component();
        assert_eq!(big.triangles.len(), 1);
        assert!((big.area() - 2.0).abs() < 1e-6);
        assert_eq!(big.vertices.len(), 3);
    }

    #[test]
    fn surface_samples_follow_area_and_lie_on_the_surface() {
        let m = two_triangles_apart();
        let pts = m.sample_surface(20000, 3);
        let far = pts.iter().filter(|p| p.x >= 5.0).count() as f64 / pts.len() as f64;
        // Areas 0.5 and 2: 80 % of the samples on the second triangle.
        assert!((far - 0.8).abs() < 0.02, "{far}");
        assert!(pts.iter().all(|p| p.z == 0.0 && p.x >= 0.0 && p.y >= 0.0));
        assert_eq!(pts, m.sample_surface(20000, 3), "seeded");
    }

    #[test]
    fn obj_round_trip_and_bad_files() {
        let dir = std::env::temp_dir().join(format!("aim-mesh-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let m = two_triangles_apart();
        m.write_obj_and_ply(&dir.join("m"), "test").unwrap();
        assert_eq!(read_obj(&dir.join("m.obj")).unwrap(), m);
        let ply = std::fs::read(dir.join("m.ply")).unwrap();
        assert!(ply.starts_with(b"ply\nformat binary_little_endian 1.0\nelement vertex 6\n"));
        std::fs::write(dir.join("bad.obj"), "v 0 0 0\nf 1 2 3\n").unwrap();
        let e = read_obj(&dir.join("bad.obj")).unwrap_err().to_string();
        assert!(e.contains("bad.obj") && e.contains("line 2"), "{e}");
    }
}
