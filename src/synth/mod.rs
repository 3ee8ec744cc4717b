//! Synthetic articulated objects with exact ground truth, in the AiM data layout.
//!
//! The AiM paper's PartNet-Mobility renders are not available here, so this module
//! builds a benchmark that mirrors them (Appendix C): eleven procedural objects
//! ([`objects::OBJECT_NAMES`]), an exact ray-cast renderer, a dataset writer in the AiM
//! layout and the ground truth (joints, PARIS-style trans.json, per-part meshes).
//!
//! # The pieces
//! - [`geometry`]: rays, boxes, cylinders, triangle meshes and a BVH.
//! - [`texture`]: procedural solid textures (albedo at a rest-frame point).
//! - [`scene`]: [`Part`] (primitives + BVH), [`Joint`], [`ArticulatedObject`], and
//!   [`PosedScene`], the object at one time that can be ray-cast.
//! - [`render`]: pinhole rendering of a posed scene to RGBA, z-depth and part ids.
//! - [`dataset`]: camera plans and the AiM-layout writer ([`write_dataset`]).
//! - [`gt`]: `gt/joints.json`, `gt/trans.json`, OBJ meshes, and their readers.
//! - [`contact_sheet`]: a grid of every object at its start and end state.
//!
//! # Ray-casting any camera model
//! The scene API is not tied to pinhole images: pose an object at motion time `t` and
//! cast arbitrary world rays (e.g. through a fisheye model):
//! ```
//! use aim::synth::{objects, Ray};
//! use glam::Vec3;
//! let fridge = objects::object("fridge").unwrap();
//! let scene = fridge.posed(0.5); // t in [0, 1]
//! let ray = Ray::new(Vec3::new(0.0, -3.0, 0.0), Vec3::Y);
//! let hit = scene.intersect(&ray, f32::INFINITY).expect("the fridge is in front");
//! // hit.t (distance in units of |dir|), hit.normal (facing the ray), hit.part (id),
//! // hit.albedo (texture colour), hit.position, hit.rest_position.
//! assert!(hit.t > 2.0 && hit.t < 3.0);
//! ```
//! Extra geometry (a hand, a table) can be added to a posed scene with
//! [`PosedScene::push`] as a [`Part`] with its own id and rigid pose, and shaded with
//! [`render::Lighting::shade`].
//!
//! # Conventions
//! World z up, object fronts face -y, units are metres, objects about one unit across
//! centred near the origin. Joint state moves linearly with motion time:
//! `q(t) = range[0] + t (range[1] - range[0])`; geometry is modelled at q = 0.

pub mod contact_sheet;
pub mod dataset;
pub mod geometry;
pub mod gt;
pub mod objects;
pub mod recording;
pub mod render;
pub mod scene;
pub mod texture;

pub use crate::motion::JointKind;
pub use dataset::{plan_views, write_dataset, DatasetSummary, PlannedView, SynthConfig};
pub use geometry::{Aabb, Ray, Shape};
pub use gt::{JointRecord, JointsFile};
pub use objects::{object, HELD_OUT_NAMES, OBJECT_NAMES};
pub use render::{camera_ray, render, RenderOptions, RenderOutput, BACKGROUND_ID};
pub use scene::{ArticulatedObject, Hit, Joint, Part, PosedScene, Primitive};
pub use texture::{Material, Pattern};
