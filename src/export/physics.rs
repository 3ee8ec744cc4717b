//! What a simulator needs beyond the visual mesh: a convex collision shape and
//! the inertial properties of each part, and the joints' effort and velocity
//! limits (`ExportConfig`).

use glam::{Mat3, Vec3};
use parry3d::mass_properties::MassProperties;
use parry3d::math::Point;
use serde::{Deserialize, Serialize};

use crate::mesh::MeshData;

/// Settings of the simulator exports (URDF, MJCF).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ExportConfig {
    /// Density of every part's collision volume (kg/m^3). The twin knows shapes,
    /// not materials: the default is a hollow appliance's mean density (a 1 m^3
    /// fridge hull -> 100 kg), to be set per object for dynamics that matter.
    pub density: f32,
    /// Joint effort limit (N m for revolute joints, N for prismatic ones).
    pub effort: f32,
    /// Joint velocity limit (rad/s for revolute joints, m/s for prismatic ones).
    pub velocity: f32,
}

impl Default for ExportConfig {
    fn default() -> Self {
        Self { density: 100.0, effort: 10.0, velocity: 1.0 }
    }
}

impl ExportConfig {
    pub fn validate(&self) -> std::result::Result<(), String> {
        for (k, v) in [("density", self.density), ("effort", self.effort), ("velocity", self.velocity)] {
            if !(v.is_finite() && v > 0.0) {
                return Err(format!("export.{k} must be a positive number, got {v}"));
            }
        }
        Ok(())
    }
}

/// A part's inertial properties in world coordinates at the start state.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Inertial {
    /// kg.
    pub mass: f32,
    /// Centre of mass.
    pub com: [f32; 3],
    /// Inertia tensor about the centre of mass, axes of the world frame:
    /// ixx, iyy, izz, ixy, ixz, iyz (kg m^2).
    pub inertia: [f32; 6],
}

/// A mesh's vertices as parry's points.
fn points(mesh: &MeshData) -> Vec<Point<f32>> {
    mesh.vertices.iter().map(|v| Point::new(v.x, v.y, v.z)).collect()
}

/// The convex hull of a mesh's vertices (None for fewer than four points not in a plane).
pub fn convex_hull(mesh: &MeshData) -> Option<MeshData> {
    let points = points(mesh);
    if points.len() < 4 {
        return None;
    }
    let (vertices, triangles) = parry3d::transformation::try_convex_hull(&points).ok()?;
    (triangles.len() >= 4)
        .then(|| MeshData { vertices: vertices.iter().map(|p| Vec3::new(p.x, p.y, p.z)).collect(), triangles })
}

/// Mass, centre of mass and inertia of a closed convex mesh (`convex_hull`'s)
/// filled at `density`; None for a hull without volume.
pub fn inertial_of_hull(hull: &MeshData, density: f32) -> Option<Inertial> {
    let m = MassProperties::from_convex_polyhedron(density, &points(hull), &hull.triangles);
    let mass = m.mass();
    if !(mass.is_finite() && mass > 0.0) {
        return None;
    }
    let t = m.reconstruct_inertia_matrix();
    let i = Mat3::from_cols_array(&[t.m11, t.m21, t.m31, t.m12, t.m22, t.m32, t.m13, t.m23, t.m33]);
    let com = m.local_com;
    Some(Inertial {
        mass,
        com: [com.x, com.y, com.z],
        inertia: [i.x_axis.x, i.y_axis.y, i.z_axis.z, i.y_axis.x, i.z_axis.x, i.z_axis.y],
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A closed axis-aligned box mesh.
    fn cuboid(min: Vec3, max: Vec3) -> MeshData {
        let mut m = MeshData::default();
        crate::synth::Shape::cuboid(min, max).tessellate(1, &mut m);
        m
    }

    #[test]
    fn a_box_has_the_textbook_mass_and_inertia() {
        // 2 x 1 x 0.5 m at 100 kg/m^3: 100 kg, I_xx = m (b^2 + c^2) / 12.
        let (min, max) = (Vec3::new(1.0, -0.5, 0.0), Vec3::new(3.0, 0.5, 0.5));
        let mut mesh = cuboid(min, max);
        // Inner points do not change the hull.
        mesh.vertices.push(Vec3::new(2.0, 0.0, 0.25));
        let hull = convex_hull(&mesh).expect("hull");
        let i = inertial_of_hull(&hull, 100.0).expect("volume");
        assert!((i.mass - 100.0).abs() < 1e-3, "{}", i.mass);
        for (a, b) in i.com.iter().zip([2.0, 0.0, 0.25]) {
            assert!((a - b).abs() < 1e-5, "{:?}", i.com);
        }
        let m = 100.0f32;
        let expect = [m * (1.0 + 0.25) / 12.0, m * (4.0 + 0.25) / 12.0, m * (4.0 + 1.0) / 12.0, 0.0, 0.0, 0.0];
        for (a, b) in i.inertia.iter().zip(expect) {
            assert!((a - b).abs() < 1e-3, "{:?} vs {expect:?}", i.inertia);
        }
    }

    #[test]
    fn flat_or_tiny_input_has_no_hull() {
        let square = MeshData {
            vertices: vec![Vec3::ZERO, Vec3::X, Vec3::Y, Vec3::new(1.0, 1.0, 0.0)],
            triangles: vec![[0, 1, 2], [1, 3, 2]],
        };
        assert!(convex_hull(&square).and_then(|h| inertial_of_hull(&h, 1.0)).is_none());
        assert!(convex_hull(&MeshData { vertices: vec![Vec3::ZERO; 3], triangles: vec![] }).is_none());
        assert!(ExportConfig { density: 0.0, ..ExportConfig::default() }.validate().is_err());
    }
}
