//! Shape metrics on meshes: Chamfer distance and 3D IoU (paper Appendix B).

use glam::Vec3;
use kiddo::{ImmutableKdTree, SquaredEuclidean};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::mesh::inside::column_crossings;
use crate::mesh::MeshData;

/// Points sampled per mesh for the Chamfer distance (as the paper).
pub const CHAMFER_SAMPLES: usize = 10_000;

/// Bi-directional Chamfer distance between two surfaces, in both forms the field uses.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ChamferDistance {
    /// The paper's form: mean nearest-neighbour distance A -> B plus B -> A, plain L2, millimetres.
    pub l2_mm: f64,
    /// The public DTA/ArtGS code's form: the same with squared distances (m^2), times 1000.
    pub squared_l2_x1000: f64,
}

/// Mean nearest-neighbour distance and squared distance from each of `from` to `to`.
fn directed(from: &[Vec3], to: &[Vec3]) -> (f64, f64) {
    let coords: Vec<[f32; 3]> = to.iter().map(|p| p.to_array()).collect();
    let tree: ImmutableKdTree<f32, 3> = ImmutableKdTree::new_from_slice(&coords);
    // Distances in parallel, summed in order: a parallel reduction's grouping
    // depends on the thread schedule, and the metric must repeat to the last bit.
    let d2: Vec<f64> =
        from.par_iter().map(|p| f64::from(tree.nearest_one::<SquaredEuclidean>(&p.to_array()).distance)).collect();
    let (sum, sum_sq) = d2.iter().fold((0.0, 0.0), |(s, s2), &d| (s + d.sqrt(), s2 + d));
    (sum / from.len() as f64, sum_sq / from.len() as f64)
}

/// Chamfer distance between two point sets (world units: metres). None if either is empty.
pub fn chamfer_points(a: &[Vec3], b: &[Vec3]) -> Option<ChamferDistance> {
    if a.is_empty() || b.is_empty() {
        return None;
    }
    let (ab, ab2) = directed(a, b);
    let (ba, ba2) = directed(b, a);
    Some(ChamferDistance { l2_mm: 1000.0 * (ab + ba), squared_l2_x1000: 1000.0 * (ab2 + ba2) })
}

/// Chamfer distance between two meshes from `CHAMFER_SAMPLES` area-uniform samples
/// each (seeded) of the surface that bounds each solid
/// ([`MeshData::sample_outer_surface`]: faces inside overlapping primitives are
/// not surface anyone could reconstruct).
pub fn chamfer_meshes(a: &MeshData, b: &MeshData, seed: u64) -> Option<ChamferDistance> {
    chamfer_meshes_sampled(a, b, seed, CHAMFER_SAMPLES)
}

/// [`chamfer_meshes`] with `samples` per mesh instead of the paper's 10k: the
/// sampling alone adds about half the sample spacing, sqrt(area / samples), to
/// each direction (16 mm on the benchmark fridge's 11 m^2 at 10k).
pub fn chamfer_meshes_sampled(a: &MeshData, b: &MeshData, seed: u64, samples: usize) -> Option<ChamferDistance> {
    chamfer_points(&a.sample_outer_surface(samples, seed), &b.sample_outer_surface(samples, seed ^ 0x9e37))
}

/// A regular grid of voxels: voxel (i, j, k) spans `min + voxel * [i, i+1) x ...`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VoxelGrid {
    pub min: Vec3,
    pub voxel: f32,
    pub dims: [usize; 3],
}

impl VoxelGrid {
    /// A grid of `voxel`-sized cells covering all of `meshes`, one empty cell of margin.
    pub fn covering(meshes: &[&MeshData], voxel: f32) -> Option<Self> {
        let (lo, hi) = meshes.iter().filter_map(|m| m.bounds()).reduce(|(a, b), (c, d)| (a.min(c), b.max(d)))?;
        let min = lo - Vec3::splat(voxel);
        let dims = (((hi - lo) / voxel).ceil().as_uvec3() + glam::UVec3::splat(2)).to_array().map(|d| d as usize);
        Some(Self { min, voxel, dims })
    }

    pub fn len(&self) -> usize {
        self.dims.iter().product()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// Solid voxelisation: a voxel is occupied when its centre is inside the mesh.
/// Inside is decided per connected component by ray parity along z (so a union
/// of overlapping closed components, like the ground-truth meshes, is the union
/// of their solids); a component that is not closed contributes only between
/// its paired crossings. Column rays sit at a fixed sub-voxel offset so they do
/// not run exactly through the edges of axis-aligned triangulated faces.
pub fn solid_voxels(mesh: &MeshData, grid: &VoxelGrid) -> Vec<bool> {
    const OFFSET: [f32; 2] = [0.5 + 0.0137, 0.5 - 0.0291];
    let [nx, ny, nz] = grid.dims;
    let (components, _) = mesh.triangle_components();
    let crossings = column_crossings(mesh, 0..mesh.triangles.len(), grid.min, grid.voxel, [nx, ny], OFFSET);
    let mut occupied = vec![false; grid.len()];
    let columns: Vec<Vec<usize>> = crossings
        .into_par_iter()
        .map(|column| {
            let mut hits: Vec<(u32, f32)> = column.iter().map(|h| (components[h.triangle as usize], h.z)).collect();
            hits.sort_by(|x, y| x.0.cmp(&y.0).then(x.1.total_cmp(&y.1)));
            let mut filled = Vec::new();
            for comp in hits.chunk_by(|x, y| x.0 == y.0) {
                for pair in comp.chunks_exact(2) {
                    let k0 = ((pair[0].1 - grid.min.z) / grid.voxel - 0.5).ceil().max(0.0) as usize;
                    let k1 =
                        (((pair[1].1 - grid.min.z) / grid.voxel - 0.5).floor() + 1.0).clamp(0.0, nz as f32) as usize;
                    filled.extend(k0..k1.max(k0));
                }
            }
            filled
        })
        .collect();
    for (col, ks) in columns.iter().enumerate() {
        for &k in ks {
            occupied[col + nx * ny * k] = true;
        }
    }
    occupied
}

/// 3D IoU (percent) of the solids of two meshes on one grid of `voxel`-sized cells.
/// None when both are empty.
pub fn iou_meshes(a: &MeshData, b: &MeshData, voxel: f32) -> Option<f64> {
    let grid = VoxelGrid::covering(&[a, b], voxel)?;
    let (va, vb) = (solid_voxels(a, &grid), solid_voxels(b, &grid));
    let (mut inter, mut union) = (0usize, 0usize);
    for (x, y) in va.iter().zip(&vb) {
        inter += usize::from(*x && *y);
        union += usize::from(*x || *y);
    }
    (union > 0).then(|| 100.0 * inter as f64 / union as f64)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synth::Shape;

    fn cube(min: Vec3, size: f32) -> MeshData {
        let mut m = MeshData::default();
        Shape::cuboid(min, min + Vec3::splat(size)).tessellate(8, &mut m);
        m
    }

    #[test]
    fn chamfer_of_two_known_point_sets() {
        // A = {0}, B = {(3,0,0) mm, (0,4,0) mm}: A->B 3 mm; B->A (3 + 4)/2 = 3.5 mm.
        let a = [Vec3::ZERO];
        let b = [Vec3::new(0.003, 0.0, 0.0), Vec3::new(0.0, 0.004, 0.0)];
        let cd = chamfer_points(&a, &b).unwrap();
        assert!((cd.l2_mm - 6.5).abs() < 1e-4, "{cd:?}");
        // Squared: 9e-6 + (9e-6 + 16e-6) / 2 = 21.5e-6 m^2, x 1000.
        assert!((cd.squared_l2_x1000 - 0.0215).abs() < 1e-7, "{cd:?}");
        assert!(chamfer_points(&a, &[]).is_none());
    }

    #[test]
    fn faces_inside_an_overlapping_primitive_are_not_surface() {
        // A 1 m cube with a 0.5 m cube sunk half into its top face: the small
        // cube's lower half and the big cube's top under it are inside the solid.
        let mut m = cube(Vec3::ZERO, 1.0);
        let small = cube(Vec3::new(0.25, 0.25, 0.75), 0.5);
        let offset = m.vertices.len() as u32;
        m.vertices.extend(&small.vertices);
        m.triangles.extend(small.triangles.iter().map(|t| t.map(|i| i + offset)));
        let samples = m.sample_outer_surface(4000, 3);
        assert_eq!(samples.len(), 4000);
        let inside = |p: &Vec3, lo: Vec3, hi: Vec3| p.cmpgt(lo + 1e-4).all() && p.cmplt(hi - 1e-4).all();
        let hidden_top =
            |p: &Vec3| (p.z - 1.0).abs() < 1e-5 && p.x > 0.2501 && p.x < 0.7499 && p.y > 0.2501 && p.y < 0.7499;
        assert!(samples.iter().all(|p| !inside(p, Vec3::ZERO, Vec3::ONE) && !hidden_top(p)));
        // Visible area: 6 - 0.25 (covered top) + 0.25 (small cube's top) + 4 x 0.5 x 0.25 (its sides above) = 6.5.
        let above = samples.iter().filter(|p| p.z > 1.0 + 1e-5).count() as f64 / samples.len() as f64;
        assert!((above - 0.75 / 6.5).abs() < 0.02, "{above}");
    }

    #[test]
    fn unit_cube_against_a_shifted_cube() {
        let a = cube(Vec3::ZERO, 1.0);
        // The same surface: only the sampling distance (10k samples on area 6 are ~25 mm
        // apart, each direction's mean nearest distance about half of that).
        let same = chamfer_meshes(&a, &a, 1).unwrap().l2_mm;
        assert!(same < 30.0, "{same}");
        // Shifted by 0.1 along x: the solids overlap in 0.9 of a cube, the union is 1.1.
        let b = cube(Vec3::new(0.1, 0.0, 0.0), 1.0);
        let iou = iou_meshes(&a, &b, 0.01).unwrap();
        assert!((iou - 100.0 * 0.9 / 1.1).abs() < 0.5, "{iou}");
        assert!((iou_meshes(&a, &a, 0.01).unwrap() - 100.0).abs() < 1e-9);
        // Chamfer of the shift: the sixth of A's samples on its x = 0 face are 0.1 from
        // B (and the same for B's x = 1.1 face), the others at most 0.1: each direction's
        // mean lies in [100/6, 100] mm.
        let cd = chamfer_meshes(&a, &b, 2).unwrap().l2_mm;
        assert!(cd > 2.0 * 100.0 / 6.0 && cd < 2.0 * 100.0, "{cd}");
    }

    #[test]
    fn overlapping_components_voxelise_as_their_union() {
        // Two unit cubes overlapping in half: union volume 1.5.
        let m = MeshData::merged([&cube(Vec3::ZERO, 1.0), &cube(Vec3::new(0.5, 0.0, 0.0), 1.0)]);
        let grid = VoxelGrid::covering(&[&m], 0.02).unwrap();
        let v = solid_voxels(&m, &grid).iter().filter(|x| **x).count() as f64 * 0.02f64.powi(3);
        assert!((v - 1.5).abs() < 0.02, "{v}");
    }
}
