//! Articulated objects (rigid parts + joints) and their posed, ray-castable state.

use std::sync::Arc;

use glam::{Affine3A, Mat3, Quat, Vec3};

use super::geometry::{Aabb, Bvh, Ray, Shape};
use super::texture::Material;
use crate::mesh::MeshData;
use crate::motion::JointKind;

/// A shape with its material, in its part's rest frame.
#[derive(Clone, Debug)]
pub struct Primitive {
    pub shape: Shape,
    pub material: Material,
}

/// A rigid part: primitives in its rest frame (the world frame at joint state 0) and a BVH over them.
#[derive(Clone, Debug)]
pub struct Part {
    pub name: String,
    pub primitives: Vec<Primitive>,
    bvh: Bvh,
}

/// A hit in a part's rest frame.
#[derive(Clone, Copy, Debug)]
pub struct LocalHit {
    pub t: f32,
    pub normal: Vec3,
    pub primitive: usize,
}

impl Part {
    pub fn new(name: impl Into<String>, primitives: Vec<Primitive>) -> Self {
        let boxes: Vec<Aabb> = primitives.iter().map(|p| p.shape.bounds()).collect();
        let bvh = Bvh::build(&boxes, 2);
        Self { name: name.into(), primitives, bvh }
    }

    /// Rest-frame bounds.
    pub fn bounds(&self) -> Aabb {
        self.bvh.bounds()
    }

    /// Closest hit of a rest-frame ray.
    pub fn intersect(&self, ray: &Ray, tmax: f32) -> Option<LocalHit> {
        let mut normal = Vec3::Z;
        let (primitive, t) = self.bvh.closest(ray, tmax, |i, tmax| {
            let (t, n) = self.primitives[i].shape.intersect(ray, tmax)?;
            normal = n;
            Some(t)
        })?;
        // `normal` belongs to the last accepted hit, which is the closest: the traversal
        // only accepts hits below the running tmax.
        Some(LocalHit { t, normal, primitive })
    }

    /// The part moved by `offset`.
    pub fn translated(&self, offset: Vec3) -> Self {
        let primitives = self
            .primitives
            .iter()
            .map(|p| Primitive { shape: p.shape.translated(offset), material: p.material })
            .collect();
        Part::new(self.name.clone(), primitives)
    }

    /// Closed triangle mesh of the part at rest (cylinders with `segments` sides).
    pub fn mesh(&self, segments: u32) -> MeshData {
        let mut m = MeshData::default();
        for p in &self.primitives {
            p.shape.tessellate(segments, &mut m);
        }
        m
    }
}

/// A joint moving `part` relative to its parent (always the static base, part 0).
///
/// The part's geometry is modelled at joint state 0; at state `q` a revolute part is
/// rotated by `q` radians about the line through `origin` along `axis` (right-hand
/// rule), a prismatic part translated by `q * axis`. During the motion video the state
/// moves linearly: `q(t) = range[0] + t * (range[1] - range[0])`, t in [0, 1].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Joint {
    pub part: usize,
    pub kind: JointKind,
    /// Unit axis.
    pub axis: Vec3,
    /// A point on the axis.
    pub origin: Vec3,
    /// State at t = 0 and t = 1 (radians or units).
    pub range: [f32; 2],
    pub parent: usize,
}

impl Joint {
    pub fn state(&self, t: f32) -> f32 {
        self.range[0] + t * (self.range[1] - self.range[0])
    }

    /// Rest frame to world at joint state `q`.
    pub fn transform_at_state(&self, q: f32) -> Affine3A {
        match self.kind {
            JointKind::Revolute => {
                let r = Affine3A::from_quat(Quat::from_axis_angle(self.axis, q));
                Affine3A::from_translation(self.origin) * r * Affine3A::from_translation(-self.origin)
            }
            JointKind::Prismatic => Affine3A::from_translation(self.axis * q),
        }
    }

    /// Rest frame to world at motion time `t`.
    pub fn transform(&self, t: f32) -> Affine3A {
        self.transform_at_state(self.state(t))
    }
}

/// Where cameras should look from: the object's front and a comfortable elevation.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ViewHint {
    /// Azimuth (degrees, from +x towards +y) of the side the moving parts face.
    pub front_azimuth_deg: f32,
    /// Elevation (degrees) of the motion video's camera path.
    pub motion_elevation_deg: f32,
    /// Camera distance from the origin.
    pub distance: f32,
}

impl Default for ViewHint {
    fn default() -> Self {
        Self { front_azimuth_deg: -90.0, motion_elevation_deg: 25.0, distance: 2.7 }
    }
}

/// An articulated object: part 0 is the static base; each other part has one joint.
#[derive(Clone, Debug)]
pub struct ArticulatedObject {
    pub name: String,
    pub parts: Vec<Arc<Part>>,
    pub joints: Vec<Joint>,
    pub view: ViewHint,
}

impl ArticulatedObject {
    /// The object moved by `offset`: its parts and its joints' axis lines with it.
    pub fn translated(&self, offset: Vec3) -> Self {
        ArticulatedObject {
            name: self.name.clone(),
            parts: self.parts.iter().map(|p| Arc::new(p.translated(offset))).collect(),
            joints: self.joints.iter().map(|j| Joint { origin: j.origin + offset, ..*j }).collect(),
            view: self.view,
        }
    }

    /// The joint that moves `part`, if any.
    pub fn joint_of(&self, part: usize) -> Option<&Joint> {
        self.joints.iter().find(|j| j.part == part)
    }

    /// Rest frame of `part` to world at motion time `t` (identity for the base).
    pub fn part_transform(&self, part: usize, t: f32) -> Affine3A {
        self.joint_of(part).map(|j| j.transform(t)).unwrap_or(Affine3A::IDENTITY)
    }

    /// The object posed at motion time `t` (0 = start state, 1 = end state).
    pub fn posed(&self, t: f32) -> PosedScene {
        let mut scene = PosedScene::default();
        for (i, part) in self.parts.iter().enumerate() {
            scene.push(part.clone(), i as u32, self.part_transform(i, t));
        }
        scene
    }

    /// World bounds of the object over the whole motion (sampled at `steps + 1` times,
    /// each part's rest bounds transformed, so conservative for boxes).
    pub fn swept_bounds(&self, steps: u32) -> Aabb {
        (0..=steps.max(1)).fold(Aabb::EMPTY, |b, i| b.union(self.posed(i as f32 / steps.max(1) as f32).bounds()))
    }

    /// Part meshes in world coordinates at motion time `t`.
    pub fn meshes_at(&self, t: f32, segments: u32) -> Vec<MeshData> {
        (0..self.parts.len()).map(|i| self.parts[i].mesh(segments).transformed(&self.part_transform(i, t))).collect()
    }
}

/// A part placed in the world.
#[derive(Clone, Debug)]
pub struct PosedPart {
    pub part: Arc<Part>,
    /// Id reported in hits (part index in its object).
    pub id: u32,
    /// Rest frame to world.
    pub to_world: Affine3A,
    to_rest: Affine3A,
    rot: Mat3,
    world_bounds: Aabb,
}

/// A ray hit in world coordinates.
#[derive(Clone, Copy, Debug)]
pub struct Hit {
    /// Ray parameter: distance in units of |ray.dir|.
    pub t: f32,
    pub position: Vec3,
    /// Unit world normal, flipped to face the ray's origin.
    pub normal: Vec3,
    pub part: u32,
    pub albedo: Vec3,
    /// Hit point in the part's rest frame (texture coordinates).
    pub rest_position: Vec3,
}

/// A set of posed parts that can be ray-cast: the object at one time, plus anything a
/// caller adds (e.g. a hand as an extra part with its own id).
#[derive(Clone, Debug, Default)]
pub struct PosedScene {
    pub parts: Vec<PosedPart>,
    bounds: Aabb,
}

impl PosedScene {
    /// Add a part placed by `to_world` (rest frame to world, rigid).
    pub fn push(&mut self, part: Arc<Part>, id: u32, to_world: Affine3A) {
        let world_bounds = part.bounds().transformed(&to_world);
        self.bounds = if self.parts.is_empty() { world_bounds } else { self.bounds.union(world_bounds) };
        let rot = Mat3::from(to_world.matrix3);
        self.parts.push(PosedPart { part, id, to_world, to_rest: to_world.inverse(), rot, world_bounds });
    }

    /// World bounds of everything in the scene.
    pub fn bounds(&self) -> Aabb {
        if self.parts.is_empty() {
            Aabb::EMPTY
        } else {
            self.bounds
        }
    }

    /// Closest hit along `ray` with `t < tmax`, with the part id and albedo there.
    pub fn intersect(&self, ray: &Ray, tmax: f32) -> Option<Hit> {
        let inv = ray.dir.recip();
        self.bounds.hit(ray.origin, inv, tmax)?;
        let mut best: Option<(usize, super::scene::LocalHit)> = None;
        let mut tmax = tmax;
        for (k, pp) in self.parts.iter().enumerate() {
            if pp.world_bounds.hit(ray.origin, inv, tmax).is_none() {
                continue;
            }
            // Rigid transform: the ray parameter is preserved.
            let local = Ray::new(pp.to_rest.transform_point3(ray.origin), pp.to_rest.transform_vector3(ray.dir));
            if let Some(h) = pp.part.intersect(&local, tmax) {
                tmax = h.t;
                best = Some((k, h));
            }
        }
        let (k, h) = best?;
        let pp = &self.parts[k];
        let rest_position = pp.to_rest.transform_point3(ray.at(h.t));
        let mut normal = (pp.rot * h.normal).normalize_or_zero();
        if normal.dot(ray.dir) > 0.0 {
            normal = -normal;
        }
        Some(Hit {
            t: h.t,
            position: ray.at(h.t),
            normal,
            part: pp.id,
            albedo: pp.part.primitives[h.primitive].material.albedo(rest_position),
            rest_position,
        })
    }
}
