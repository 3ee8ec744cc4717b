//! Which connected component's solid a point lies in: the test that keeps
//! samples on faces hidden inside overlapping primitives out of the Chamfer
//! distance ([`MeshData::sample_outer_surface`]).
//!
//! Inside means a generalized winding number above 1/4 (1 inside, 1/2 on the
//! surface, 0 outside, whatever the triangles' orientation). Summed over every
//! triangle that is exact for any component but costs a component's whole
//! triangle count per point, and a TSDF part mesh has hundreds of thousands
//! (the evaluation of one fridge spent a minute there). A closed, consistently
//! oriented component's winding number is an integer away from its surface, the
//! same over any cell no triangle reaches, and equal to the signed count of the
//! surface crossings of a ray: such a component (every edge used as often in
//! each direction) gets a grid of cells with the
//! winding number cast along z at two ray offsets per column; a point in a cell
//! no triangle's bounds come within a cell of, where both rays agree, reads the
//! grid, and every other point (near the surface, or on a ray that grazed an
//! edge) the exact sum. The decisions are the exact sum's.

use std::collections::HashMap;

use glam::Vec3;
use rayon::prelude::*;

use super::MeshData;

/// Components with at most this many triangles are always summed exactly.
const EXACT_TRIANGLES: usize = 4096;
/// Cells along the largest side of a component's grid.
const GRID_CELLS: f32 = 192.0;
/// The two ray offsets within a column (fractions of a cell), off the centre so
/// that rays do not run exactly through the edges of axis-aligned faces.
const RAY_OFFSETS: [[f32; 2]; 2] = [[0.5 + 0.0137, 0.5 - 0.0291], [0.5 - 0.2113, 0.5 + 0.1871]];
/// A grid cell whose winding number the grid does not decide.
const UNDECIDED: i8 = -1;

/// One surface crossing of a column ray along +z.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Crossing {
    pub triangle: u32,
    pub z: f32,
    /// The triangle faces +z (its corners run anticlockwise seen from above).
    pub up: bool,
}

/// The crossings of the rays along z through the columns of an `nx` x `ny` grid
/// of `voxel`-sized cells from `min` (each ray at `offset` within its column) with
/// `triangles` of `mesh`, per column (x fastest), in triangle order.
pub(crate) fn column_crossings(
    mesh: &MeshData,
    triangles: impl Iterator<Item = usize>,
    min: Vec3,
    voxel: f32,
    [nx, ny]: [usize; 2],
    offset: [f32; 2],
) -> Vec<Vec<Crossing>> {
    let mut crossings: Vec<Vec<Crossing>> = vec![Vec::new(); nx * ny];
    for t in triangles {
        let [a, b, c] = mesh.corners(&mesh.triangles[t]);
        let lo = ((a.min(b).min(c) - min) / voxel).floor();
        let hi = ((a.max(b).max(c) - min) / voxel).ceil();
        let (i0, i1) = ((lo.x.max(0.0)) as usize, (hi.x.max(0.0) as usize).min(nx));
        let (j0, j1) = ((lo.y.max(0.0)) as usize, (hi.y.max(0.0) as usize).min(ny));
        let det = (b.x - a.x) * (c.y - a.y) - (c.x - a.x) * (b.y - a.y);
        if det.abs() < 1e-20 {
            continue; // parallel to the rays
        }
        for j in j0..j1 {
            for i in i0..i1 {
                let px = min.x + voxel * (i as f32 + offset[0]);
                let py = min.y + voxel * (j as f32 + offset[1]);
                let u = ((px - a.x) * (c.y - a.y) - (c.x - a.x) * (py - a.y)) / det;
                let v = ((b.x - a.x) * (py - a.y) - (px - a.x) * (b.y - a.y)) / det;
                if u >= 0.0 && v >= 0.0 && u + v <= 1.0 {
                    let z = a.z + u * (b.z - a.z) + v * (c.z - a.z);
                    crossings[i + nx * j].push(Crossing { triangle: t as u32, z, up: det > 0.0 });
                }
            }
        }
    }
    crossings
}

/// The solids of a mesh's connected components, for inside tests.
pub(crate) struct ComponentSolids<'a> {
    mesh: &'a MeshData,
    /// The component of each triangle.
    pub component: Vec<u32>,
    members: Vec<Vec<usize>>,
    bounds: Vec<(Vec3, Vec3)>,
    grids: Vec<Option<WindingGrid>>,
}

impl<'a> ComponentSolids<'a> {
    pub fn new(mesh: &'a MeshData) -> Self {
        let (component, count) = mesh.triangle_components();
        let mut members: Vec<Vec<usize>> = vec![Vec::new(); count];
        for (t, &c) in component.iter().enumerate() {
            members[c as usize].push(t);
        }
        let bounds: Vec<(Vec3, Vec3)> = members
            .iter()
            .map(|ts| {
                ts.iter()
                    .flat_map(|&t| mesh.corners(&mesh.triangles[t]))
                    .fold((Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)), |(lo, hi), v| {
                        (lo.min(v), hi.max(v))
                    })
            })
            .collect();
        let grids = members
            .par_iter()
            .zip(&bounds)
            .map(|(ts, &(lo, hi))| {
                (ts.len() > EXACT_TRIANGLES && closed_and_oriented(mesh, ts))
                    .then(|| WindingGrid::new(mesh, ts, lo, hi))
            })
            .collect();
        Self { mesh, component, members, bounds, grids }
    }

    pub fn count(&self) -> usize {
        self.members.len()
    }

    /// Whether `p` lies inside (or on) the solid of a component other than `own`.
    pub fn inside_another(&self, own: usize, p: Vec3) -> bool {
        let eps = Vec3::splat(1e-6);
        (0..self.count()).any(|c| {
            let (lo, hi) = self.bounds[c];
            c != own && p.cmpge(lo - eps).all() && p.cmple(hi + eps).all() && self.inside(c, p)
        })
    }

    fn inside(&self, c: usize, p: Vec3) -> bool {
        match self.grids[c].as_ref().and_then(|g| g.winding(p)) {
            Some(w) => w >= 1,
            None => self.mesh.winding_number(&self.members[c], p).abs() > 0.25,
        }
    }
}

/// Whether every edge of `triangles` is used as often in one direction as in the
/// other: a closed surface whose triangles all face the same side (non-manifold
/// edges, which surface nets make where four cells meet, included), whose
/// winding number is an integer off the surface.
fn closed_and_oriented(mesh: &MeshData, triangles: &[usize]) -> bool {
    // Per undirected edge, uses in one direction minus uses in the other.
    let mut balance: HashMap<(u32, u32), i32> = HashMap::with_capacity(3 * triangles.len());
    for &t in triangles {
        let [a, b, c] = mesh.triangles[t];
        for (p, q) in [(a, b), (b, c), (c, a)] {
            *balance.entry((p.min(q), p.max(q))).or_default() += if p < q { 1 } else { -1 };
        }
    }
    balance.values().all(|&n| n == 0)
}

/// A closed, oriented component's |winding number| per cell (`UNDECIDED` where
/// the surface may pass or the two rays disagree).
struct WindingGrid {
    min: Vec3,
    voxel: f32,
    dims: [usize; 3],
    cells: Vec<i8>,
}

impl WindingGrid {
    fn new(mesh: &MeshData, triangles: &[usize], lo: Vec3, hi: Vec3) -> Self {
        let voxel = ((hi - lo).max_element() / GRID_CELLS).max(1e-6);
        let min = lo - Vec3::splat(voxel);
        let dims = (((hi - lo) / voxel).ceil().as_uvec3() + glam::UVec3::splat(2)).to_array().map(|d| d as usize);
        let [nx, ny, nz] = dims;
        let casts: Vec<Vec<Vec<Crossing>>> = RAY_OFFSETS
            .par_iter()
            .map(|&offset| column_crossings(mesh, triangles.iter().copied(), min, voxel, [nx, ny], offset))
            .collect();
        let mut cells = vec![0i8; nx * ny * nz];
        // Per column, each ray's signed count of the crossings above each cell centre.
        let columns: Vec<Vec<i8>> =
            (0..nx * ny)
                .into_par_iter()
                .map(|col| {
                    let counts: Vec<Vec<i32>> = casts
                        .iter()
                        .map(|cast| {
                            let mut hits = cast[col].clone();
                            hits.sort_by(|x, y| x.z.total_cmp(&y.z));
                            let mut above: i32 = hits.iter().map(|h| if h.up { 1 } else { -1 }).sum();
                            let mut next = 0;
                            (0..nz)
                                .map(|k| {
                                    let zc = min.z + voxel * (k as f32 + 0.5);
                                    while next < hits.len() && hits[next].z <= zc {
                                        above -= if hits[next].up { 1 } else { -1 };
                                        next += 1;
                                    }
                                    above.abs()
                                })
                                .collect()
                        })
                        .collect();
                    (0..nz)
                        .map(|k| {
                            if counts[0][k] == counts[1][k] {
                                counts[0][k].min(i8::MAX as i32) as i8
                            } else {
                                UNDECIDED
                            }
                        })
                        .collect()
                })
                .collect();
        for (col, ws) in columns.iter().enumerate() {
            for (k, &w) in ws.iter().enumerate() {
                cells[col + nx * ny * k] = w;
            }
        }
        // Cells a triangle's bounds come within a cell of: the surface may pass there.
        for &t in triangles {
            let [a, b, c] = mesh.corners(&mesh.triangles[t]);
            let lo = ((a.min(b).min(c) - min) / voxel).floor() - Vec3::ONE;
            let hi = ((a.max(b).max(c) - min) / voxel).floor() + Vec3::ONE;
            let range = |axis: usize| {
                let n = dims[axis] as f32;
                (lo[axis].clamp(0.0, n - 1.0) as usize)..=(hi[axis].clamp(0.0, n - 1.0) as usize)
            };
            for k in range(2) {
                for j in range(1) {
                    for i in range(0) {
                        cells[i + nx * (j + ny * k)] = UNDECIDED;
                    }
                }
            }
        }
        Self { min, voxel, dims, cells }
    }

    /// |winding number| at `p` when the grid decides it.
    fn winding(&self, p: Vec3) -> Option<i8> {
        let g = ((p - self.min) / self.voxel).floor();
        if g.cmplt(Vec3::ZERO).any() {
            return Some(0);
        }
        let [i, j, k] = g.to_array().map(|x| x as usize);
        let [nx, ny, nz] = self.dims;
        if i >= nx || j >= ny || k >= nz {
            return Some(0);
        }
        let w = self.cells[i + nx * (j + ny * k)];
        (w != UNDECIDED).then_some(w)
    }
}

#[cfg(test)]
mod tests {
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    use super::*;
    use crate::synth::Shape;

    #[test]
    fn the_grid_decides_as_the_exact_winding_number_does() {
        // A closed cylinder of 8000 triangles (tilted, so its faces are not
        // axis-aligned), a box sunk half into its side and a small cylinder
        // through it: the large one is tested through its grid.
        let mut m = MeshData::default();
        Shape::cylinder(Vec3::new(0.5, 0.5, 0.5), Vec3::new(0.3, 0.2, 1.0), 0.4, 0.9).tessellate(2000, &mut m);
        Shape::cuboid(Vec3::new(0.7, 0.4, 0.3), Vec3::new(1.1, 0.6, 0.7)).tessellate(1, &mut m);
        Shape::cylinder(Vec3::new(0.5, 0.5, 0.5), Vec3::X, 0.05, 1.2).tessellate(24, &mut m);
        let solids = ComponentSolids::new(&m);
        assert_eq!(solids.count(), 3);
        assert!(solids.grids[0].is_some() && solids.grids[1].is_none() && solids.grids[2].is_none());

        // Points anywhere around, and points on every surface (where the
        // winding number is 1/2 or the sums are closest to the threshold).
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let mut points: Vec<Vec3> =
            (0..8_000).map(|_| Vec3::new(rng.random(), rng.random(), rng.random()) * 1.6 - 0.3).collect();
        points.extend(m.sample_triangles(8_000, &mut rng).into_iter().map(|(_, p)| p));
        let (mut by_grid, mut inside) = (0, 0);
        for (n, p) in points.iter().enumerate() {
            for c in 0..3 {
                let exact = m.winding_number(&solids.members[c], *p).abs() > 0.25;
                assert_eq!(solids.inside(c, *p), exact, "component {c} at {p}");
                if c == 0 && n < 8_000 {
                    by_grid += usize::from(solids.grids[0].as_ref().unwrap().winding(*p).is_some());
                    inside += usize::from(exact);
                }
            }
        }
        // The grid decided most of the points around, inside and outside alike.
        assert!(by_grid > 6_000, "{by_grid} of 8000");
        assert!(inside > 400 && inside < 7_600, "{inside}");
    }

    #[test]
    fn closed_surfaces_are_those_using_each_edge_as_often_both_ways() {
        let mut closed = MeshData::default();
        Shape::cylinder(Vec3::ZERO, Vec3::Z, 1.0, 1.0).tessellate(1500, &mut closed);
        let ts: Vec<usize> = (0..closed.triangles.len()).collect();
        assert!(closed_and_oriented(&closed, &ts));
        let mut flipped = closed.clone();
        flipped.triangles[7].swap(1, 2);
        assert!(!closed_and_oriented(&flipped, &ts));
        assert!(!closed_and_oriented(&closed, &ts[..ts.len() - 1]), "open");
        // Two tetrahedra sharing an edge (used four times, twice each way: a
        // non-manifold edge, as surface nets make) bound a closed solid.
        let tet = |[a, b, c, d]: [u32; 4]| [[a, c, b], [a, b, d], [b, c, d], [c, a, d]];
        let two = MeshData {
            vertices: vec![Vec3::ZERO, Vec3::X, Vec3::Y, Vec3::Z, -Vec3::Y, -Vec3::Z],
            triangles: [tet([0, 1, 2, 3]), tet([0, 1, 4, 5])].concat(),
        };
        assert!(closed_and_oriented(&two, &(0..8).collect::<Vec<_>>()));
    }
}
