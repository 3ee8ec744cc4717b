//! Exact ray casting against boxes, cylinders and triangle meshes, with a BVH.
//!
//! Everything here works in one coordinate frame (a part's rest frame); posing is done
//! by [`super::scene`], which transforms rays into that frame.

use std::sync::Arc;

use glam::{Mat3, Vec3};

use crate::mesh::MeshData;

/// Hits closer than this along a ray are ignored (self-intersection guard).
pub const RAY_EPS: f32 = 1e-6;

/// A ray `origin + t * dir`; `dir` need not be unit length (distances are in units of |dir|).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Ray {
    pub origin: Vec3,
    pub dir: Vec3,
}

impl Ray {
    pub fn new(origin: Vec3, dir: Vec3) -> Self {
        Self { origin, dir }
    }

    pub fn at(&self, t: f32) -> Vec3 {
        self.origin + t * self.dir
    }
}

/// An axis-aligned bounding box.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Aabb {
    pub min: Vec3,
    pub max: Vec3,
}

impl Default for Aabb {
    fn default() -> Self {
        Self::EMPTY
    }
}

impl Aabb {
    pub const EMPTY: Aabb = Aabb { min: Vec3::splat(f32::INFINITY), max: Vec3::splat(f32::NEG_INFINITY) };

    pub fn from_points(points: impl IntoIterator<Item = Vec3>) -> Self {
        points.into_iter().fold(Self::EMPTY, |b, p| b.grow(p))
    }

    pub fn grow(self, p: Vec3) -> Self {
        Self { min: self.min.min(p), max: self.max.max(p) }
    }

    pub fn union(self, o: Aabb) -> Self {
        Self { min: self.min.min(o.min), max: self.max.max(o.max) }
    }

    pub fn center(&self) -> Vec3 {
        0.5 * (self.min + self.max)
    }

    pub fn extent(&self) -> Vec3 {
        (self.max - self.min).max(Vec3::ZERO)
    }

    pub fn is_empty(&self) -> bool {
        self.min.cmpgt(self.max).any()
    }

    pub fn corners(&self) -> [Vec3; 8] {
        let (a, b) = (self.min, self.max);
        [
            Vec3::new(a.x, a.y, a.z),
            Vec3::new(b.x, a.y, a.z),
            Vec3::new(a.x, b.y, a.z),
            Vec3::new(b.x, b.y, a.z),
            Vec3::new(a.x, a.y, b.z),
            Vec3::new(b.x, a.y, b.z),
            Vec3::new(a.x, b.y, b.z),
            Vec3::new(b.x, b.y, b.z),
        ]
    }

    /// The box of this box's corners under an affine map.
    pub fn transformed(&self, m: &glam::Affine3A) -> Self {
        if self.is_empty() {
            return *self;
        }
        Self::from_points(self.corners().iter().map(|&c| m.transform_point3(c)))
    }

    /// Entry distance of the ray into the box if it enters before `tmax` (slab test).
    #[inline]
    pub fn hit(&self, origin: Vec3, inv_dir: Vec3, tmax: f32) -> Option<f32> {
        let t1 = (self.min - origin) * inv_dir;
        let t2 = (self.max - origin) * inv_dir;
        let tnear = t1.min(t2).max_element().max(0.0);
        let tfar = t1.max(t2).min_element().min(tmax);
        // NaN (0 * inf on a slab boundary) compares false: treated as a miss, which is
        // only possible for rays exactly grazing a face.
        (tnear <= tfar).then_some(tnear)
    }
}

/// A bounding volume hierarchy over items with boxes (median split on the longest axis).
#[derive(Clone, Debug, Default)]
pub struct Bvh {
    nodes: Vec<BvhNode>,
    /// Item indices, permuted so each leaf owns a contiguous range.
    items: Vec<u32>,
}

#[derive(Clone, Copy, Debug)]
struct BvhNode {
    aabb: Aabb,
    /// Leaf: first item; inner: index of the left child (the right child follows its subtree).
    first: u32,
    /// Leaf: item count (> 0); inner: 0, and `right` holds the right child.
    count: u32,
    right: u32,
}

impl Bvh {
    /// Build over item boxes; leaves hold at most `leaf_size` items.
    pub fn build(boxes: &[Aabb], leaf_size: usize) -> Self {
        let mut bvh = Bvh { nodes: Vec::with_capacity(boxes.len() * 2), items: (0..boxes.len() as u32).collect() };
        if !boxes.is_empty() {
            let centers: Vec<Vec3> = boxes.iter().map(|b| b.center()).collect();
            bvh.build_node(boxes, &centers, 0, boxes.len(), leaf_size.max(1));
        }
        bvh
    }

    fn build_node(&mut self, boxes: &[Aabb], centers: &[Vec3], lo: usize, hi: usize, leaf: usize) -> u32 {
        let idx = self.nodes.len() as u32;
        let aabb = self.items[lo..hi].iter().fold(Aabb::EMPTY, |b, &i| b.union(boxes[i as usize]));
        self.nodes.push(BvhNode { aabb, first: lo as u32, count: (hi - lo) as u32, right: 0 });
        if hi - lo <= leaf {
            return idx;
        }
        let cb = Aabb::from_points(self.items[lo..hi].iter().map(|&i| centers[i as usize]));
        let e = cb.extent();
        let axis = if e.x >= e.y && e.x >= e.z {
            0
        } else if e.y >= e.z {
            1
        } else {
            2
        };
        let mid = (lo + hi) / 2;
        self.items[lo..hi]
            .select_nth_unstable_by(mid - lo, |&a, &b| centers[a as usize][axis].total_cmp(&centers[b as usize][axis]));
        let left = self.build_node(boxes, centers, lo, mid, leaf);
        let right = self.build_node(boxes, centers, mid, hi, leaf);
        let n = &mut self.nodes[idx as usize];
        n.first = left;
        n.count = 0;
        n.right = right;
        idx
    }

    pub fn bounds(&self) -> Aabb {
        self.nodes.first().map(|n| n.aabb).unwrap_or(Aabb::EMPTY)
    }

    /// Closest-hit traversal. `test(item, tmax)` returns the item's hit distance if it is
    /// below `tmax`; the closest `(item, t)` is returned.
    #[inline]
    pub fn closest(
        &self,
        ray: &Ray,
        mut tmax: f32,
        mut test: impl FnMut(usize, f32) -> Option<f32>,
    ) -> Option<(usize, f32)> {
        if self.nodes.is_empty() {
            return None;
        }
        let inv = ray.dir.recip();
        let mut best = None;
        let mut stack = [0u32; 64];
        let mut sp = 0usize;
        self.nodes[0].aabb.hit(ray.origin, inv, tmax)?;
        let mut node = 0u32;
        loop {
            let n = self.nodes[node as usize];
            if n.count > 0 {
                for &item in &self.items[n.first as usize..(n.first + n.count) as usize] {
                    if let Some(t) = test(item as usize, tmax) {
                        if t < tmax {
                            tmax = t;
                            best = Some((item as usize, t));
                        }
                    }
                }
            } else {
                let (a, b) = (n.first, n.right);
                let ta = self.nodes[a as usize].aabb.hit(ray.origin, inv, tmax);
                let tb = self.nodes[b as usize].aabb.hit(ray.origin, inv, tmax);
                match (ta, tb) {
                    (Some(x), Some(y)) => {
                        let (near, far) = if x <= y { (a, b) } else { (b, a) };
                        if sp < stack.len() {
                            stack[sp] = far;
                            sp += 1;
                        }
                        node = near;
                        continue;
                    }
                    (Some(_), None) => {
                        node = a;
                        continue;
                    }
                    (None, Some(_)) => {
                        node = b;
                        continue;
                    }
                    (None, None) => {}
                }
            }
            // Pop, skipping nodes now beyond the closest hit.
            loop {
                if sp == 0 {
                    return best;
                }
                sp -= 1;
                let cand = stack[sp];
                if self.nodes[cand as usize].aabb.hit(ray.origin, inv, tmax).is_some() {
                    node = cand;
                    break;
                }
            }
        }
    }
}

/// A box with its own orientation: `rot` maps box axes to the enclosing frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BoxShape {
    pub center: Vec3,
    pub half: Vec3,
    pub rot: Mat3,
}

/// A capped cylinder; its axis is the local z axis (`rot` maps local to the enclosing frame).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CylinderShape {
    pub center: Vec3,
    pub radius: f32,
    pub half_height: f32,
    pub rot: Mat3,
}

/// A triangle mesh with a BVH; triangles are two-sided.
#[derive(Clone, Debug)]
pub struct TriMesh {
    pub vertices: Vec<Vec3>,
    pub triangles: Vec<[u32; 3]>,
    bvh: Bvh,
}

impl TriMesh {
    pub fn new(vertices: Vec<Vec3>, triangles: Vec<[u32; 3]>) -> Self {
        let boxes: Vec<Aabb> =
            triangles.iter().map(|t| Aabb::from_points(t.iter().map(|&i| vertices[i as usize]))).collect();
        let bvh = Bvh::build(&boxes, 4);
        Self { vertices, triangles, bvh }
    }

    /// A prism: a planar polygon (counter-clockwise in the xy plane of `rot`) extruded by
    /// `thickness` along the local z axis, centred on `center`. Convex polygons only.
    pub fn extruded_convex_polygon(polygon: &[glam::Vec2], thickness: f32, center: Vec3, rot: Mat3) -> Self {
        let n = polygon.len() as u32;
        let h = 0.5 * thickness;
        let mut vertices = Vec::with_capacity(2 * polygon.len());
        for z in [-h, h] {
            for p in polygon {
                vertices.push(center + rot * Vec3::new(p.x, p.y, z));
            }
        }
        let mut triangles = Vec::new();
        for i in 1..n.saturating_sub(1) {
            triangles.push([0, i + 1, i]);
            triangles.push([n, n + i, n + i + 1]);
        }
        for i in 0..n {
            let j = (i + 1) % n;
            triangles.push([i, j, n + j]);
            triangles.push([i, n + j, n + i]);
        }
        Self::new(vertices, triangles)
    }

    pub fn bounds(&self) -> Aabb {
        self.bvh.bounds()
    }

    /// Closest hit: (t, geometric normal, not oriented).
    pub fn intersect(&self, ray: &Ray, tmax: f32) -> Option<(f32, Vec3)> {
        let (tri, t) = self.bvh.closest(ray, tmax, |i, tmax| {
            let [a, b, c] = self.triangles[i];
            intersect_triangle(
                ray,
                self.vertices[a as usize],
                self.vertices[b as usize],
                self.vertices[c as usize],
                tmax,
            )
        })?;
        let [a, b, c] = self.triangles[tri];
        let (a, b, c) = (self.vertices[a as usize], self.vertices[b as usize], self.vertices[c as usize]);
        Some((t, (b - a).cross(c - a).normalize_or_zero()))
    }
}

/// Möller-Trumbore; two-sided.
#[inline]
pub fn intersect_triangle(ray: &Ray, a: Vec3, b: Vec3, c: Vec3, tmax: f32) -> Option<f32> {
    let e1 = b - a;
    let e2 = c - a;
    let p = ray.dir.cross(e2);
    let det = e1.dot(p);
    if det.abs() < 1e-12 {
        return None;
    }
    let inv = 1.0 / det;
    let s = ray.origin - a;
    let u = s.dot(p) * inv;
    if !(0.0..=1.0).contains(&u) {
        return None;
    }
    let q = s.cross(e1);
    let v = ray.dir.dot(q) * inv;
    if v < 0.0 || u + v > 1.0 {
        return None;
    }
    let t = e2.dot(q) * inv;
    (t > RAY_EPS && t < tmax).then_some(t)
}

/// A solid primitive.
#[derive(Clone, Debug)]
pub enum Shape {
    Box(BoxShape),
    Cylinder(CylinderShape),
    Mesh(Arc<TriMesh>),
}

impl Shape {
    /// An axis-aligned box from its corners.
    pub fn cuboid(min: Vec3, max: Vec3) -> Self {
        Shape::Box(BoxShape { center: 0.5 * (min + max), half: 0.5 * (max - min).abs(), rot: Mat3::IDENTITY })
    }

    /// A box with orientation `rot` (box axes as columns).
    pub fn oriented_box(center: Vec3, half: Vec3, rot: Mat3) -> Self {
        Shape::Box(BoxShape { center, half, rot })
    }

    /// A cylinder along `axis` (any direction) through `center`.
    pub fn cylinder(center: Vec3, axis: Vec3, radius: f32, height: f32) -> Self {
        let z = axis.normalize();
        let helper = if z.x.abs() < 0.9 { Vec3::X } else { Vec3::Y };
        let x = helper.cross(z).normalize();
        let y = z.cross(x);
        Shape::Cylinder(CylinderShape { center, radius, half_height: 0.5 * height, rot: Mat3::from_cols(x, y, z) })
    }

    /// The same shape moved by `offset`.
    pub fn translated(&self, offset: Vec3) -> Self {
        match self {
            Shape::Box(b) => Shape::Box(BoxShape { center: b.center + offset, ..*b }),
            Shape::Cylinder(c) => Shape::Cylinder(CylinderShape { center: c.center + offset, ..*c }),
            Shape::Mesh(m) => Shape::Mesh(Arc::new(TriMesh::new(
                m.vertices.iter().map(|v| *v + offset).collect(),
                m.triangles.clone(),
            ))),
        }
    }

    pub fn bounds(&self) -> Aabb {
        match self {
            Shape::Box(b) => {
                let e = b.rot.x_axis.abs() * b.half.x + b.rot.y_axis.abs() * b.half.y + b.rot.z_axis.abs() * b.half.z;
                Aabb { min: b.center - e, max: b.center + e }
            }
            Shape::Cylinder(c) => {
                let (x, y, z) = (c.rot.x_axis.abs(), c.rot.y_axis.abs(), c.rot.z_axis.abs());
                let e = (x + y) * c.radius + z * c.half_height;
                // Tighter per axis: radius * sqrt(1 - axis_i^2) + half_height * |axis_i|.
                let a = c.rot.z_axis;
                let tight = (Vec3::ONE - a * a).max(Vec3::ZERO).map(f32::sqrt) * c.radius + a.abs() * c.half_height;
                let e = e.min(tight);
                Aabb { min: c.center - e, max: c.center + e }
            }
            Shape::Mesh(m) => m.bounds(),
        }
    }

    /// Closest hit beyond [`RAY_EPS`] and below `tmax`: (t, outward geometric normal).
    #[inline]
    pub fn intersect(&self, ray: &Ray, tmax: f32) -> Option<(f32, Vec3)> {
        match self {
            Shape::Box(b) => {
                let rt = b.rot.transpose();
                let o = rt * (ray.origin - b.center);
                let d = rt * ray.dir;
                let inv = d.recip();
                let t1 = (-b.half - o) * inv;
                let t2 = (b.half - o) * inv;
                let tnear = t1.min(t2).max_element();
                let tfar = t1.max(t2).min_element();
                // Written so NaN (a grazing ray) counts as a miss.
                if tnear.partial_cmp(&tfar).is_none_or(|o| o.is_gt()) || tfar <= RAY_EPS {
                    return None;
                }
                let t = if tnear > RAY_EPS { tnear } else { tfar };
                if t >= tmax {
                    return None;
                }
                let p = (o + t * d) / b.half;
                let a = p.abs();
                let n = if a.x >= a.y && a.x >= a.z {
                    Vec3::new(p.x.signum(), 0.0, 0.0)
                } else if a.y >= a.z {
                    Vec3::new(0.0, p.y.signum(), 0.0)
                } else {
                    Vec3::new(0.0, 0.0, p.z.signum())
                };
                Some((t, b.rot * n))
            }
            Shape::Cylinder(c) => {
                let rt = c.rot.transpose();
                let o = rt * (ray.origin - c.center);
                let d = rt * ray.dir;
                let mut best: Option<(f32, Vec3)> = None;
                let mut consider = |t: f32, n: Vec3| {
                    if t > RAY_EPS && t < tmax && best.is_none_or(|(bt, _)| t < bt) {
                        best = Some((t, n));
                    }
                };
                // Side.
                let a = d.x * d.x + d.y * d.y;
                if a > 1e-20 {
                    let b = o.x * d.x + o.y * d.y;
                    let cc = o.x * o.x + o.y * o.y - c.radius * c.radius;
                    let disc = b * b - a * cc;
                    if disc >= 0.0 {
                        let s = disc.sqrt();
                        for t in [(-b - s) / a, (-b + s) / a] {
                            let z = o.z + t * d.z;
                            if z.abs() <= c.half_height {
                                let p = o + t * d;
                                consider(t, Vec3::new(p.x, p.y, 0.0) / c.radius);
                            }
                        }
                    }
                }
                // Caps.
                if d.z.abs() > 1e-20 {
                    for s in [-1.0f32, 1.0] {
                        let t = (s * c.half_height - o.z) / d.z;
                        let p = o + t * d;
                        if p.x * p.x + p.y * p.y <= c.radius * c.radius {
                            consider(t, Vec3::new(0.0, 0.0, s));
                        }
                    }
                }
                best.map(|(t, n)| (t, c.rot * n))
            }
            Shape::Mesh(m) => m.intersect(ray, tmax),
        }
    }

    /// Append a closed triangle mesh of the shape (cylinders with `segments` sides).
    pub fn tessellate(&self, segments: u32, out: &mut MeshData) {
        match self {
            Shape::Box(b) => {
                let base = out.vertices.len() as u32;
                for i in 0..8u32 {
                    let s = Vec3::new(
                        if i & 1 == 0 { -1.0 } else { 1.0 },
                        if i & 2 == 0 { -1.0 } else { 1.0 },
                        if i & 4 == 0 { -1.0 } else { 1.0 },
                    );
                    out.vertices.push(b.center + b.rot * (s * b.half));
                }
                // Outward-facing (counter-clockwise seen from outside).
                const FACES: [[u32; 4]; 6] =
                    [[0, 4, 6, 2], [1, 3, 7, 5], [0, 1, 5, 4], [2, 6, 7, 3], [0, 2, 3, 1], [4, 5, 7, 6]];
                for f in FACES {
                    out.triangles.push([base + f[0], base + f[1], base + f[2]]);
                    out.triangles.push([base + f[0], base + f[2], base + f[3]]);
                }
            }
            Shape::Cylinder(c) => {
                let n = segments.max(3);
                let base = out.vertices.len() as u32;
                for z in [-c.half_height, c.half_height] {
                    for i in 0..n {
                        let a = i as f32 / n as f32 * std::f32::consts::TAU;
                        out.vertices.push(c.center + c.rot * Vec3::new(c.radius * a.cos(), c.radius * a.sin(), z));
                    }
                }
                out.vertices.push(c.center + c.rot * Vec3::new(0.0, 0.0, -c.half_height));
                out.vertices.push(c.center + c.rot * Vec3::new(0.0, 0.0, c.half_height));
                let (bc, tc) = (base + 2 * n, base + 2 * n + 1);
                for i in 0..n {
                    let j = (i + 1) % n;
                    out.triangles.push([base + i, base + j, base + n + j]);
                    out.triangles.push([base + i, base + n + j, base + n + i]);
                    out.triangles.push([bc, base + j, base + i]);
                    out.triangles.push([tc, base + n + i, base + n + j]);
                }
            }
            Shape::Mesh(m) => {
                let base = out.vertices.len() as u32;
                out.vertices.extend_from_slice(&m.vertices);
                out.triangles.extend(m.triangles.iter().map(|t| [t[0] + base, t[1] + base, t[2] + base]));
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn box_hit_distance_and_normal() {
        let b = Shape::cuboid(Vec3::new(-1.0, -1.0, -1.0), Vec3::new(1.0, 1.0, 1.0));
        let (t, n) = b.intersect(&Ray::new(Vec3::new(0.0, 0.0, 5.0), Vec3::NEG_Z), f32::INFINITY).unwrap();
        assert!((t - 4.0).abs() < 1e-6);
        assert_eq!(n, Vec3::Z);
        assert!(b.intersect(&Ray::new(Vec3::new(2.0, 0.0, 5.0), Vec3::NEG_Z), f32::INFINITY).is_none());
    }

    #[test]
    fn rotated_box_matches_its_tessellation() {
        let rot = Mat3::from_rotation_z(0.4) * Mat3::from_rotation_x(0.3);
        let shape = Shape::oriented_box(Vec3::new(0.1, 0.2, -0.1), Vec3::new(0.3, 0.2, 0.1), rot);
        let mut mesh = MeshData::default();
        shape.tessellate(8, &mut mesh);
        let tm = TriMesh::new(mesh.vertices, mesh.triangles);
        for k in 0..200 {
            let a = k as f32 * 0.37;
            let o = Vec3::new(3.0 * a.cos(), 3.0 * a.sin(), 0.7 * (k as f32 * 0.11).sin());
            let target = Vec3::new(0.1 + 0.3 * (a * 1.3).sin(), 0.2 + 0.2 * (a * 0.7).cos(), -0.1);
            let ray = Ray::new(o, target - o);
            let x = shape.intersect(&ray, f32::INFINITY).map(|h| h.0);
            let y = tm.intersect(&ray, f32::INFINITY).map(|h| h.0);
            match (x, y) {
                (Some(x), Some(y)) => assert!((x - y).abs() < 1e-4, "{x} vs {y}"),
                (None, None) => {}
                other => panic!("box and its mesh disagree: {other:?}"),
            }
        }
    }

    #[test]
    fn cylinder_side_and_cap() {
        let c = Shape::cylinder(Vec3::ZERO, Vec3::Z, 0.5, 2.0);
        let (t, n) = c.intersect(&Ray::new(Vec3::new(3.0, 0.0, 0.0), Vec3::NEG_X), f32::INFINITY).unwrap();
        assert!((t - 2.5).abs() < 1e-5 && (n - Vec3::X).length() < 1e-5);
        let (t, n) = c.intersect(&Ray::new(Vec3::new(0.2, 0.0, 4.0), Vec3::NEG_Z), f32::INFINITY).unwrap();
        assert!((t - 3.0).abs() < 1e-5 && (n - Vec3::Z).length() < 1e-5);
        assert!(c.intersect(&Ray::new(Vec3::new(0.6, 0.0, 4.0), Vec3::NEG_Z), f32::INFINITY).is_none());
    }

    #[test]
    fn bvh_finds_the_closest_of_many() {
        let boxes: Vec<Shape> = (0..50)
            .map(|i| {
                let x = i as f32 * 0.1;
                Shape::cuboid(Vec3::new(x, -0.02, -0.02), Vec3::new(x + 0.05, 0.02, 0.02))
            })
            .collect();
        let aabbs: Vec<Aabb> = boxes.iter().map(|b| b.bounds()).collect();
        let bvh = Bvh::build(&aabbs, 2);
        let ray = Ray::new(Vec3::new(10.0, 0.0, 0.0), Vec3::NEG_X);
        let (i, t) = bvh.closest(&ray, f32::INFINITY, |i, tmax| boxes[i].intersect(&ray, tmax).map(|h| h.0)).unwrap();
        assert_eq!(i, 49);
        assert!((t - (10.0 - 4.95)).abs() < 1e-4);
    }
}
