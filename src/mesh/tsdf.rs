//! Meshes from trained Gaussians: render depth and alpha from many views
//! around the set, fuse them into a truncated signed distance volume (TSDF),
//! extract the zero level set, keep the largest component.
//!
//! As the official AiM code: voxel 0.004 of the object's size, truncation 5
//! voxels. Fusion is a plain projective TSDF: a voxel in front of the rendered
//! surface (or seen through an empty pixel) is free (+1), one within the
//! truncation band in front or `behind_voxels` behind gets
//! `(depth - z) / truncation`, one farther behind is occluded in that view and
//! left alone (a narrower band behind than in front keeps thin walls thin); observations are weighted by how
//! squarely the pixel's ray meets the surface. Voxels no view observes are inside
//! the object (every view around it sees only its outside), which closes the
//! surface. The isosurface is extracted by Naive Surface Nets
//! (`fast-surface-nets`, docs/architecture.md says why not marching cubes).

use glam::Vec3;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::MeshData;
use crate::camera::{Camera, Intrinsics};
use crate::error::{Error, Result};
use crate::render::{render, RenderOptions};
use crate::splat::{sigmoid, GaussianSet};

/// How a Gaussian set is turned into a mesh.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TsdfConfig {
    /// Voxel edge as a fraction of the object's size (largest bounding-box side).
    pub voxel_fraction: f32,
    /// Truncation band in voxels (in front of the surface, and the normalisation).
    pub truncation_voxels: f32,
    /// How far behind the rendered surface (voxels) an observation still counts.
    /// Less than the truncation: thin walls (a door, a drawer side) are thinner
    /// than the band, and a full band behind the front face would reach past the
    /// back face and push the surface out on both sides.
    pub behind_voxels: f32,
    /// Views on a Fibonacci sphere around the set.
    pub views: usize,
    /// Depth renders have this many pixels per voxel across the object (at most
    /// `max_resolution` wide). A pixel much larger than a voxel smears each
    /// depth over several voxels: seen edge-on, a 2 cm panel covers whole pixels
    /// around it and the surface swells by about a pixel.
    pub pixels_per_voxel: f32,
    pub max_resolution: u32,
    /// Rendered alpha above which a pixel is a surface hit; below it, free space.
    pub alpha_threshold: f32,
    /// Gaussians below this opacity are left out of the bounds (floaters).
    pub min_opacity: f32,
    /// At most this many voxels per axis (the voxel grows past it).
    pub max_voxels_per_axis: usize,
}

impl Default for TsdfConfig {
    fn default() -> Self {
        Self {
            voxel_fraction: 0.004,
            truncation_voxels: 5.0,
            behind_voxels: 1.5,
            views: 64,
            pixels_per_voxel: 1.5,
            max_resolution: 1024,
            alpha_threshold: 0.5,
            min_opacity: 0.1,
            max_voxels_per_axis: 320,
        }
    }
}

/// Bounds of the Gaussians with opacity >= `min_opacity`: per axis the 0.2 % and
/// 99.8 % quantiles of their centres (so a few floaters far away do not set the
/// grid), grown by 2 % of the extent; None if no Gaussian is opaque enough.
pub fn gaussian_bounds(gs: &GaussianSet, min_opacity: f32) -> Option<(Vec3, Vec3)> {
    let opaque: Vec<usize> = (0..gs.len()).filter(|&i| sigmoid(gs.opacity_logits[i]) >= min_opacity).collect();
    if opaque.is_empty() {
        return None;
    }
    let (mut lo, mut hi) = (Vec3::ZERO, Vec3::ZERO);
    for axis in 0..3 {
        let mut c: Vec<f32> = opaque.iter().map(|&i| gs.means[3 * i + axis]).collect();
        c.sort_by(f32::total_cmp);
        let q = |f: f64| c[((c.len() - 1) as f64 * f).round() as usize];
        lo[axis] = q(0.002);
        hi[axis] = q(0.998);
    }
    let grow = Vec3::splat(0.02 * (hi - lo).max_element());
    Some((lo - grow, hi + grow))
}

/// The object size (largest side of the bounds) of several Gaussian sets together.
pub fn object_size<'a>(sets: impl IntoIterator<Item = &'a GaussianSet>, min_opacity: f32) -> Option<f32> {
    let (lo, hi) = sets
        .into_iter()
        .filter_map(|g| gaussian_bounds(g, min_opacity))
        .reduce(|(a, b), (c, d)| (a.min(c), b.max(d)))?;
    Some((hi - lo).max_element())
}

/// Directions spread evenly over the sphere (Fibonacci lattice).
pub(crate) fn sphere_directions(n: usize) -> Vec<Vec3> {
    let golden = std::f32::consts::PI * (3.0 - 5f32.sqrt());
    (0..n)
        .map(|k| {
            let z = 1.0 - 2.0 * (k as f32 + 0.5) / n as f32;
            let r = (1.0 - z * z).max(0.0).sqrt();
            let a = golden * k as f32;
            Vec3::new(r * a.cos(), r * a.sin(), z)
        })
        .collect()
}

/// Cameras on a sphere around (`lo`, `hi`), each seeing the whole bounding sphere.
fn cameras_around(lo: Vec3, hi: Vec3, voxel: f32, cfg: &TsdfConfig) -> Vec<Camera> {
    let center = 0.5 * (lo + hi);
    let radius = 0.5 * (hi - lo).length().max(1e-6);
    let fov = 60f32.to_radians();
    let distance = radius / (0.5 * fov).sin() * 1.05;
    // Pixel size at the centre's depth, over the image width 2 d tan(fov / 2).
    let wanted = cfg.pixels_per_voxel * 2.0 * distance * (0.5 * fov).tan() / voxel;
    let resolution = (wanted.ceil() as u32).clamp(16, cfg.max_resolution.max(16));
    let intr = Intrinsics::from_fov_x(resolution, resolution, fov);
    sphere_directions(cfg.views)
        .into_iter()
        .map(|d| {
            let up = if d.z.abs() > 0.95 { Vec3::X } else { Vec3::Z };
            Camera::look_at(intr, center + distance * d, center, up)
        })
        .collect()
}

/// One view's depth (camera z of the surface) and the weight of its
/// observations per pixel: where alpha is high enough, the depth and |cos| of
/// the angle between the pixel's ray and the surface normal; where it is not
/// (free space), depth +inf and weight 1, whose observation min(inf /
/// truncation, 1) = 1 is free space's value, so the fusion needs no case for it.
struct DepthView {
    camera: Camera,
    depth: Vec<f32>,
    weight: Vec<f32>,
}

impl DepthView {
    /// Depth where the alpha is high enough, weighted by how squarely the ray
    /// meets the surface (normals from the depth map's central differences). At
    /// grazing angles, near silhouettes, one pixel spans a large depth range and
    /// its depth says little about the voxels it covers: such observations
    /// would thicken the surface, so they count for little.
    fn new(camera: Camera, depth: &[f32], alpha: &[f32], alpha_threshold: f32) -> Self {
        let (w, h) = (camera.width() as usize, camera.height() as usize);
        let k = camera.intrinsics;
        let z = |x: usize, y: usize| (alpha[y * w + x] >= alpha_threshold).then(|| depth[y * w + x] / alpha[y * w + x]);
        let point = |x: usize, y: usize, d: f32| {
            Vec3::new((x as f32 + 0.5 - k.cx) / k.fx * d, (y as f32 + 0.5 - k.cy) / k.fy * d, d)
        };
        let (mut out_depth, mut out_weight) = (vec![f32::INFINITY; w * h], vec![1.0f32; w * h]);
        for y in 0..h {
            for x in 0..w {
                let Some(d) = z(x, y) else { continue };
                let neighbour = |dx: isize, dy: isize| {
                    let (nx, ny) = (x.checked_add_signed(dx)?, y.checked_add_signed(dy)?);
                    (nx < w && ny < h).then(|| z(nx, ny).map(|nd| point(nx, ny, nd))).flatten()
                };
                let c = point(x, y, d);
                // A missing neighbour (silhouette, image edge) stands in as the pixel itself.
                let at = |dx, dy| neighbour(dx, dy).unwrap_or(c);
                let n = (at(1, 0) - at(-1, 0)).cross(at(0, 1) - at(0, -1));
                let weight = if n.length_squared() > 0.0 { n.normalize().dot(c.normalize()).abs() } else { 0.0 };
                out_depth[y * w + x] = d;
                out_weight[y * w + x] = weight.max(0.05);
            }
        }
        Self { camera, depth: out_depth, weight: out_weight }
    }

    /// Add this view's observations of the voxels (x, `py`, `pz`), x =
    /// `origin_x` + `voxel` * i for each i, to `sum` and `weight`: a voxel in
    /// front of the image's surface or in free space adds its truncated signed
    /// distance (at most 1) times the pixel's weight; one farther than `behind`
    /// behind the surface, or out of the image, adds nothing (a sum of +0.0,
    /// which leaves it as it was). Without branches: which case a voxel is in
    /// changes from one to the next, and mispredicted branches cost more than
    /// the arithmetic.
    #[allow(clippy::too_many_arguments)]
    fn observe_row(
        &self,
        origin_x: f32,
        voxel: f32,
        py: f32,
        pz: f32,
        truncation: f32,
        behind: f32,
        sum: &mut [f32],
        weight: &mut [f32],
    ) {
        // Within the maps by construction; the clamp lets the compiler drop the bounds checks.
        let last = self.depth.len().min(self.weight.len()) - 1;
        for (i, (sum, weight)) in sum.iter_mut().zip(weight.iter_mut()).enumerate() {
            let (inside, pixel, z) = self.camera.landing(Vec3::new(origin_x + voxel * i as f32, py, pz));
            let pixel = if inside { pixel } else { 0 }.min(last);
            let sdf = self.depth[pixel] - z;
            // A NaN depth counts (as +1, `min` passing over the NaN), as it always has.
            let counts = inside & ((sdf >= -behind) | sdf.is_nan());
            let w = if counts { self.weight[pixel] } else { 0.0 };
            *sum += if counts { w * (sdf / truncation).min(1.0) } else { 0.0 };
            *weight += w;
        }
    }
}

/// A TSDF volume on a regular grid: `origin` is the centre of voxel (0, 0, 0).
pub struct TsdfVolume {
    pub origin: Vec3,
    pub voxel: f32,
    pub dims: [usize; 3],
    /// Normalised signed distance in [-1, 1] per voxel, x fastest; positive outside.
    pub values: Vec<f32>,
}

impl TsdfVolume {
    fn index(&self, x: usize, y: usize, z: usize) -> usize {
        x + self.dims[0] * (y + self.dims[1] * z)
    }

    /// The zero level set as a mesh in world coordinates (all components).
    pub fn surface(&self) -> MeshData {
        use fast_surface_nets::ndshape::{RuntimeShape, Shape};
        use fast_surface_nets::{surface_nets, SurfaceNetsBuffer};
        // Pad by one free voxel on every side so surfaces touching the grid's edge close.
        let [nx, ny, nz] = self.dims.map(|d| d as u32 + 2);
        let shape = RuntimeShape::<u32, 3>::new([nx, ny, nz]);
        let mut sdf = vec![1.0f32; shape.usize()];
        for z in 0..self.dims[2] {
            for y in 0..self.dims[1] {
                for x in 0..self.dims[0] {
                    sdf[shape.linearize([x as u32 + 1, y as u32 + 1, z as u32 + 1]) as usize] =
                        self.values[self.index(x, y, z)];
                }
            }
        }
        let mut buffer = SurfaceNetsBuffer::default();
        surface_nets(&sdf, &shape, [0; 3], [nx - 1, ny - 1, nz - 1], &mut buffer);
        // Padded index p is voxel p - 1.
        let vertices =
            buffer.positions.iter().map(|p| self.origin + self.voxel * (Vec3::from(*p) - Vec3::ONE)).collect();
        let triangles = buffer.indices.chunks_exact(3).map(|t| [t[0], t[1], t[2]]).collect();
        MeshData { vertices, triangles }
    }
}

/// Fuse depth renders of `gs` into a TSDF volume. `object_size` sets the voxel
/// (`voxel_fraction` of it), so all parts of one object share a voxel size.
pub fn fuse_gaussians(gs: &GaussianSet, object_size: f32, cfg: &TsdfConfig) -> Result<TsdfVolume> {
    if !(object_size.is_finite() && object_size > 0.0) {
        return Err(Error::Config(format!("mesh extraction: object size {object_size} must be positive")));
    }
    let (lo, hi) = gaussian_bounds(gs, cfg.min_opacity)
        .ok_or_else(|| Error::Other(format!("mesh extraction: no Gaussian with opacity >= {}", cfg.min_opacity)))?;
    let mut voxel = cfg.voxel_fraction * object_size;
    let truncation = cfg.truncation_voxels * voxel;
    let margin = Vec3::splat(2.0 * truncation);
    let (lo, hi) = (lo - margin, hi + margin);
    voxel = voxel.max((hi - lo).max_element() / cfg.max_voxels_per_axis as f32);
    let dims = ((hi - lo) / voxel).ceil().as_uvec3().max(glam::UVec3::ONE).to_array().map(|d| d as usize);

    let options = RenderOptions { background: Vec3::ZERO, sh_degree: Some(0), background_image: None };
    let views: Vec<DepthView> = cameras_around(lo, hi, voxel, cfg)
        .into_iter()
        .map(|camera| {
            let r = render(gs, &camera, &options);
            DepthView::new(camera, &r.image.depth, &r.image.alpha, cfg.alpha_threshold)
        })
        .collect();

    let origin = lo + Vec3::splat(0.5 * voxel);
    let behind = cfg.behind_voxels * voxel;
    let slice = dims[0] * dims[1];
    let mut values = vec![-1.0f32; slice * dims[2]];
    values.par_chunks_mut(slice).enumerate().for_each(|(z, plane)| {
        // View by view over the whole plane: each view's depth map is then read
        // in order (one voxel after another lands on neighbouring pixels), not
        // all 64 maps in turn for every voxel. Each voxel still sums its views
        // in the same order.
        let (mut sum, mut weight) = (vec![0.0f32; slice], vec![0.0f32; slice]);
        let pz = origin.z + voxel * z as f32;
        for v in &views {
            for (y, (sum, weight)) in sum.chunks_exact_mut(dims[0]).zip(weight.chunks_exact_mut(dims[0])).enumerate() {
                v.observe_row(origin.x, voxel, origin.y + voxel * y as f32, pz, truncation, behind, sum, weight);
            }
        }
        for ((value, &sum), &weight) in plane.iter_mut().zip(&sum).zip(&weight) {
            if weight > 0.0 {
                *value = sum / weight;
            }
        }
    });
    Ok(TsdfVolume { origin, voxel, dims, values })
}

/// The mesh of a Gaussian set: TSDF fusion, isosurface, largest component.
pub fn mesh_gaussians(gs: &GaussianSet, object_size: f32, cfg: &TsdfConfig) -> Result<MeshData> {
    let mesh = fuse_gaussians(gs, object_size, cfg)?.surface().largest_component();
    if mesh.is_empty() {
        return Err(Error::Other("mesh extraction: the fused volume has no surface".into()));
    }
    Ok(mesh)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Opaque flat Gaussians tiling a sphere of radius `r` (discs tangent to it,
    /// 1 mm thick), as trained 3DGS puts them on a surface.
    fn sphere_gaussians(r: f32, n: usize) -> GaussianSet {
        let spacing = (4.0 * std::f32::consts::PI * r * r / n as f32).sqrt();
        let mut gs = GaussianSet::new(0);
        for d in sphere_directions(n) {
            let q = glam::Quat::from_rotation_arc(Vec3::Z, d);
            let log_scale = Vec3::new(spacing, spacing, 0.001).map(f32::ln);
            gs.push(d * r, log_scale, [q.w, q.x, q.y, q.z], crate::splat::logit(0.95), [0.0; 3], &[]);
        }
        gs
    }

    #[test]
    fn sphere_mesh_matches_the_analytic_sphere() {
        let r = 0.25;
        let gs = sphere_gaussians(r, 32000);
        let cfg = TsdfConfig { voxel_fraction: 0.008, views: 32, ..TsdfConfig::default() };
        let mesh = mesh_gaussians(&gs, 2.0 * r, &cfg).expect("a surface");
        let voxel = cfg.voxel_fraction * 2.0 * r;
        let radial: Vec<f32> = mesh.vertices.iter().map(|v| (v.length() - r).abs()).collect();
        let mean = radial.iter().sum::<f32>() / radial.len() as f32;
        let signed = mesh.vertices.iter().map(|v| v.length() - r).sum::<f32>() / radial.len() as f32;
        let max = radial.iter().copied().fold(0.0, f32::max);
        assert!(mean < voxel, "mean radial error {mean} m (signed {signed}; voxel {voxel})");
        assert!(max < 3.0 * voxel, "max radial error {max} m (voxel {voxel})");
        let area = mesh.area();
        let sphere = 4.0 * std::f32::consts::PI * r * r;
        assert!((area / sphere - 1.0).abs() < 0.06, "area {area} vs {sphere}");
        assert_eq!(mesh.triangle_components().1, 1, "one closed surface");
        // Chamfer against the analytic sphere, densely sampled so that the sampling
        // distance (~3 mm at 100k points) stays below the voxel: within two voxels.
        let exact: Vec<Vec3> = sphere_directions(100_000).into_iter().map(|d| d * r).collect();
        let cd = crate::eval::shape::chamfer_points(&mesh.sample_surface(100_000, 1), &exact).unwrap();
        assert!(cd.l2_mm < 2000.0 * f64::from(voxel), "{cd:?}");
    }

    #[test]
    fn nothing_opaque_is_an_error_not_a_panic() {
        let mut gs = sphere_gaussians(0.2, 100);
        gs.opacity_logits.iter_mut().for_each(|o| *o = -10.0);
        assert!(mesh_gaussians(&gs, 0.4, &TsdfConfig::default()).is_err());
        assert!(mesh_gaussians(&GaussianSet::new(0), 0.4, &TsdfConfig::default()).is_err());
        assert!(fuse_gaussians(&sphere_gaussians(0.2, 100), 0.0, &TsdfConfig::default()).is_err());
    }
}
