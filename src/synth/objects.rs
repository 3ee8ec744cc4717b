//! The eleven procedural articulated objects of the benchmark (mirroring the AiM paper's
//! Appendix C selection from PartNet-Mobility).
//!
//! World frame: z up, the object's front faces -y, everything within about one unit
//! and centred near the origin. Part 0 is the static base; parts 1.. each have one joint
//! whose parent is part 0. Geometry is modelled at joint state 0 (closed doors, drawers
//! in); a joint's `range[0]` (its state at t = 0) may differ from 0.

use std::f32::consts::PI;
use std::sync::Arc;

use glam::{Mat3, Vec2, Vec3};

use super::geometry::{Shape, TriMesh};
use super::scene::{ArticulatedObject, Joint, Part, Primitive, ViewHint};
use super::texture::{Material, Pattern};
use crate::error::{Error, Result};
use crate::motion::JointKind;

/// Names accepted by [`object`], in benchmark order.
pub const OBJECT_NAMES: [&str; 11] = [
    "fridge",
    "oven",
    "washer",
    "storage",
    "scissors",
    "blade",
    "usb",
    "storage_door_drawer",
    "fridge_two_doors",
    "storage_complex",
    "table_complex",
];

/// Objects kept out of the benchmark (`aim synth NAME`, `aim bench suite --objects`):
/// painted, nearly textureless surfaces, joints whose axes, signs and ranges no
/// benchmark object has, and shapes of their own. Nothing is tuned on them; they
/// check that a change decided on the benchmark holds on objects it was not
/// decided on (docs/synth.md).
pub const HELD_OUT_NAMES: [&str; 7] =
    ["microwave", "chest", "nightstand", "laptop", "dishwasher", "sideboard", "wall_cabinet"];

/// Build an object by name; an unknown name is an error listing the valid names.
pub fn object(name: &str) -> Result<ArticulatedObject> {
    Ok(match name {
        "fridge" => fridge(),
        "oven" => oven(),
        "washer" => washer(),
        "storage" => storage(),
        "scissors" => scissors(),
        "blade" => blade(),
        "usb" => usb(),
        "storage_door_drawer" => storage_door_drawer(),
        "fridge_two_doors" => fridge_two_doors(),
        "storage_complex" => storage_complex(),
        "table_complex" => table_complex(),
        "microwave" => microwave(),
        "chest" => chest(),
        "nightstand" => nightstand(),
        "laptop" => laptop(),
        "dishwasher" => dishwasher(),
        "sideboard" => sideboard(),
        "wall_cabinet" => wall_cabinet(),
        _ => {
            return Err(Error::Config(format!(
                "unknown object {name:?}; valid objects: {} (held out of the benchmark: {})",
                OBJECT_NAMES.join(", "),
                HELD_OUT_NAMES.join(", ")
            )))
        }
    })
}

// ---------------------------------------------------------------- materials

fn rgb(r: f32, g: f32, b: f32) -> Vec3 {
    Vec3::new(r, g, b)
}

fn enamel() -> Material {
    Material::new(Pattern::Speckle, rgb(0.86, 0.86, 0.83), rgb(0.45, 0.52, 0.6), 9.0)
}
fn steel() -> Material {
    Material::new(Pattern::Brushed, rgb(0.62, 0.64, 0.67), rgb(0.12, 0.1, 0.08), 9.0)
}
fn dark_plastic() -> Material {
    Material::new(Pattern::Speckle, rgb(0.2, 0.21, 0.24), rgb(0.6, 0.58, 0.5), 11.0)
}
fn liner() -> Material {
    Material::new(Pattern::Tiles, rgb(0.72, 0.8, 0.86), rgb(0.35, 0.4, 0.45), 9.0)
}
fn oak() -> Material {
    Material::new(Pattern::Wood, rgb(0.78, 0.56, 0.34), rgb(0.48, 0.3, 0.15), 5.0)
}
fn walnut() -> Material {
    Material::new(Pattern::Wood, rgb(0.5, 0.33, 0.2), rgb(0.27, 0.15, 0.08), 6.0)
}
fn pale_wood() -> Material {
    Material::new(Pattern::Wood, rgb(0.88, 0.78, 0.6), rgb(0.66, 0.52, 0.34), 7.0)
}
fn glass() -> Material {
    Material::new(Pattern::Marble, rgb(0.14, 0.2, 0.26), rgb(0.45, 0.58, 0.65), 3.0)
}
fn red() -> Material {
    Material::new(Pattern::Speckle, rgb(0.78, 0.16, 0.12), rgb(0.96, 0.82, 0.3), 10.0)
}
fn orange() -> Material {
    Material::new(Pattern::Speckle, rgb(0.93, 0.5, 0.1), rgb(0.25, 0.12, 0.05), 12.0)
}
fn green() -> Material {
    Material::new(Pattern::Marble, rgb(0.25, 0.6, 0.3), rgb(0.85, 0.95, 0.7), 5.0)
}
fn blue() -> Material {
    Material::new(Pattern::Marble, rgb(0.2, 0.36, 0.72), rgb(0.85, 0.9, 0.96), 4.0)
}
fn yellow() -> Material {
    Material::new(Pattern::Tiles, rgb(0.92, 0.8, 0.3), rgb(0.4, 0.3, 0.1), 14.0)
}
fn cream() -> Material {
    Material::new(Pattern::Marble, rgb(0.9, 0.86, 0.76), rgb(0.55, 0.5, 0.42), 3.0)
}
/// Paint: one colour with only a faint low-frequency shading (the held-out objects).
fn paint(r: f32, g: f32, b: f32) -> Material {
    Material::new(Pattern::Plain, rgb(r, g, b), rgb(r, g, b), 4.0)
}

// ---------------------------------------------------------------- builders

fn bx(min: [f32; 3], max: [f32; 3], m: Material) -> Primitive {
    Primitive { shape: Shape::cuboid(Vec3::from(min), Vec3::from(max)), material: m }
}

fn cyl(center: [f32; 3], axis: Vec3, radius: f32, height: f32, m: Material) -> Primitive {
    Primitive { shape: Shape::cylinder(Vec3::from(center), axis, radius, height), material: m }
}

fn prism(polygon: &[[f32; 2]], thickness: f32, center: [f32; 3], m: Material) -> Primitive {
    let poly: Vec<Vec2> = polygon.iter().map(|p| Vec2::from(*p)).collect();
    let mesh = TriMesh::extruded_convex_polygon(&poly, thickness, Vec3::from(center), Mat3::IDENTITY);
    Primitive { shape: Shape::Mesh(Arc::new(mesh)), material: m }
}

/// A box open at its front (-y face): back, left, right, bottom and top walls.
fn open_front_shell(min: [f32; 3], max: [f32; 3], wall: f32, m: Material) -> Vec<Primitive> {
    let [x0, y0, z0] = min;
    let [x1, y1, z1] = max;
    vec![
        bx([x0, y1 - wall, z0], [x1, y1, z1], m),
        bx([x0, y0, z0], [x0 + wall, y1 - wall, z1], m),
        bx([x1 - wall, y0, z0], [x1, y1 - wall, z1], m),
        bx([x0 + wall, y0, z0], [x1 - wall, y1 - wall, z0 + wall], m),
        bx([x0 + wall, y0, z1 - wall], [x1 - wall, y1 - wall, z1], m),
    ]
}

/// A drawer: front panel in x0..x1, z0..z1 from y = front_y - 0.02 to front_y, an
/// open-topped tray behind it reaching `depth` back, 2 cm in from the panel's sides,
/// and a bar handle.
fn drawer(x: [f32; 2], z: [f32; 2], front_y: f32, depth: f32, front: Material, tray: Material) -> Vec<Primitive> {
    let mut v = drawer_box(x, z, front_y, depth, front, tray);
    let hz = 0.5 * (z[0] + z[1]) + 0.15 * (z[1] - z[0]);
    let hw = (0.3 * (x[1] - x[0])).min(0.2);
    v.extend(handle_x([0.5 * (x[0] + x[1]), front_y - 0.02, hz], hw, steel()));
    v
}

/// `drawer` without its handle.
fn drawer_box(x: [f32; 2], z: [f32; 2], front_y: f32, depth: f32, front: Material, tray: Material) -> Vec<Primitive> {
    let [x0, x1] = x;
    let [z0, z1] = z;
    let (ix0, ix1) = (x0 + 0.02, x1 - 0.02);
    let (tz0, tz1) = (z0 + 0.01, z1 - 0.04);
    let yb = front_y + depth;
    let w = 0.012;
    vec![
        bx([x0, front_y - 0.02, z0], [x1, front_y, z1], front),
        bx([ix0, front_y, tz0], [ix1, yb, tz0 + w], tray),
        bx([ix0, front_y, tz0 + w], [ix0 + w, yb, tz1], tray),
        bx([ix1 - w, front_y, tz0 + w], [ix1, yb, tz1], tray),
        bx([ix0 + w, yb - w, tz0 + w], [ix1 - w, yb, tz1], tray),
    ]
}

/// A horizontal bar handle along x, standing off the face at y = `face[1]` towards -y.
fn handle_x(face: [f32; 3], length: f32, m: Material) -> Vec<Primitive> {
    let [x, y, z] = face;
    let h = 0.5 * length;
    vec![
        cyl([x, y - 0.03, z], Vec3::X, 0.011, length, m),
        bx([x - h + 0.01, y - 0.03, z - 0.007], [x - h + 0.025, y, z + 0.007], m),
        bx([x + h - 0.025, y - 0.03, z - 0.007], [x + h - 0.01, y, z + 0.007], m),
    ]
}

/// A vertical bar handle along z, standing off the face at y = `face[1]` towards -y.
fn handle_z(face: [f32; 3], length: f32, m: Material) -> Vec<Primitive> {
    let [x, y, z] = face;
    let h = 0.5 * length;
    vec![
        cyl([x, y - 0.03, z], Vec3::Z, 0.011, length, m),
        bx([x - 0.007, y - 0.03, z - h + 0.01], [x + 0.007, y, z - h + 0.025], m),
        bx([x - 0.007, y - 0.03, z + h - 0.025], [x + 0.007, y, z + h - 0.01], m),
    ]
}

/// A revolute door slab (front face at y0 - thickness .. y0) with a vertical handle.
fn door(x: [f32; 2], z: [f32; 2], y0: f32, thickness: f32, m: Material, handle_at_x: f32) -> Vec<Primitive> {
    let mut v = vec![bx([x[0], y0 - thickness, z[0]], [x[1], y0, z[1]], m)];
    let zc = 0.5 * (z[0] + z[1]);
    let len = (0.4 * (z[1] - z[0])).min(0.3);
    v.extend(handle_z([handle_at_x, y0 - thickness, zc], len, steel()));
    v
}

fn part(name: &str, prims: Vec<Primitive>) -> Arc<Part> {
    Arc::new(Part::new(name, prims))
}

fn revolute(part: usize, axis: Vec3, origin: [f32; 3], range_deg: [f32; 2]) -> Joint {
    Joint {
        part,
        kind: JointKind::Revolute,
        axis: axis.normalize(),
        origin: Vec3::from(origin),
        range: range_deg.map(|d| d * PI / 180.0),
        parent: 0,
    }
}

fn prismatic(part: usize, axis: Vec3, range: [f32; 2]) -> Joint {
    Joint { part, kind: JointKind::Prismatic, axis: axis.normalize(), origin: Vec3::ZERO, range, parent: 0 }
}

fn obj(name: &str, parts: Vec<Arc<Part>>, joints: Vec<Joint>, view: ViewHint) -> ArticulatedObject {
    ArticulatedObject { name: name.into(), parts, joints, view }
}

/// Bottles, cartons and boxes on a shelf at height `z` (static contents revealed by opening).
fn shelf_items(x0: f32, x1: f32, y: f32, z: f32, salt: usize) -> Vec<Primitive> {
    let mats = [red(), orange(), green(), blue(), yellow(), cream()];
    let mut v = Vec::new();
    let n = (((x1 - x0) / 0.13) as usize).max(1);
    for k in 0..n {
        let x = x0 + (k as f32 + 0.5) * (x1 - x0) / n as f32;
        let m = mats[(k + salt) % mats.len()];
        if (k + salt).is_multiple_of(2) {
            let h = 0.1 + 0.03 * ((k + salt) % 3) as f32;
            v.push(cyl([x, y, z + 0.5 * h], Vec3::Z, 0.035, h, m));
        } else {
            let h = 0.08 + 0.02 * ((k + salt) % 4) as f32;
            v.push(bx([x - 0.04, y - 0.04, z], [x + 0.04, y + 0.03, z + h], m));
        }
    }
    v
}

// ---------------------------------------------------------------- objects

/// Fridge: one door hinged on the right, opening 0 -> 110 deg, shelves and food inside.
pub fn fridge() -> ArticulatedObject {
    let mut body = open_front_shell([-0.3, -0.25, -0.5], [0.3, 0.3, 0.5], 0.03, enamel());
    body.push(bx([-0.27, 0.255, -0.47], [0.27, 0.27, 0.47], liner()));
    for (k, z) in [-0.17f32, 0.1, 0.3].into_iter().enumerate() {
        body.push(bx([-0.27, -0.15, z - 0.015], [0.27, 0.255, z], glass()));
        body.extend(shelf_items(-0.25, 0.25, 0.1, z, 2 * k + 1));
    }
    body.push(bx([-0.26, -0.14, -0.47], [0.26, 0.25, -0.35], blue()));
    body.push(bx([-0.3, -0.27, -0.5], [0.3, -0.25, -0.46], dark_plastic()));
    let mut d = door([-0.3, 0.3], [-0.46, 0.5], -0.25, 0.05, enamel(), -0.24);
    d.push(bx([-0.26, -0.25, -0.42], [0.26, -0.245, 0.46], liner()));
    for z in [-0.3, 0.0, 0.25] {
        d.push(bx([-0.22, -0.245, z], [0.22, -0.19, z + 0.07], red()));
    }
    obj(
        "fridge",
        vec![part("body", body), part("door", d)],
        vec![revolute(1, Vec3::Z, [0.3, -0.3, 0.0], [0.0, 110.0])],
        ViewHint::default(),
    )
}

/// Oven: door hinged at the bottom, 0 -> 90 deg; knobs, window, rack inside.
pub fn oven() -> ArticulatedObject {
    let mut body = open_front_shell([-0.35, -0.27, -0.325], [0.35, 0.3, 0.2], 0.03, steel());
    body.push(bx([-0.35, -0.27, 0.2], [0.35, 0.3, 0.325], enamel()));
    body.push(bx([-0.32, -0.275, 0.22], [0.32, -0.27, 0.31], dark_plastic()));
    for x in [-0.25, -0.12, 0.12, 0.25] {
        body.push(cyl([x, -0.29, 0.265], Vec3::Y, 0.03, 0.03, cream()));
    }
    body.push(bx([-0.32, 0.265, -0.295], [0.32, 0.27, 0.17], dark_plastic()));
    body.push(bx([-0.32, -0.2, -0.295], [0.32, 0.265, -0.29], dark_plastic()));
    for k in 0..7 {
        let x = -0.27 + 0.09 * k as f32;
        body.push(bx([x - 0.006, -0.2, -0.02], [x + 0.006, 0.26, -0.008], steel()));
    }
    body.push(bx([-0.32, -0.2, -0.026], [0.32, -0.185, -0.008], steel()));
    body.push(cyl([-0.1, 0.05, -0.008 + 0.04], Vec3::Z, 0.09, 0.08, orange()));
    body.push(bx([0.05, -0.05, -0.008], [0.25, 0.15, 0.04], red()));
    let mut d = vec![bx([-0.34, -0.3, -0.3], [0.34, -0.27, 0.19], steel())];
    d.push(bx([-0.24, -0.305, -0.16], [0.24, -0.3, 0.1], glass()));
    d.extend(handle_x([0.0, -0.3, 0.15], 0.5, steel()));
    obj(
        "oven",
        vec![part("body", body), part("door", d)],
        vec![revolute(1, Vec3::X, [0.0, -0.3, -0.3], [0.0, 90.0])],
        ViewHint { motion_elevation_deg: 30.0, ..ViewHint::default() },
    )
}

/// Washer: a round door hinged on the left, 0 -> -60 deg about +z.
pub fn washer() -> ArticulatedObject {
    let mut body = vec![bx([-0.3, -0.26, -0.425], [0.3, 0.3, 0.425], enamel())];
    body.push(bx([-0.28, -0.27, 0.3], [0.28, -0.26, 0.4], dark_plastic()));
    body.push(cyl([0.18, -0.28, 0.35], Vec3::Y, 0.035, 0.02, steel()));
    body.push(bx([-0.22, -0.265, 0.33], [0.0, -0.27, 0.37], green()));
    body.push(cyl([0.0, -0.2615, -0.02], Vec3::Y, 0.235, 0.003, steel()));
    body.push(cyl([0.0, -0.263, -0.02], Vec3::Y, 0.19, 0.006, glass()));
    body.push(bx([-0.27, -0.275, -0.1], [-0.24, -0.26, 0.06], dark_plastic()));
    let d = vec![
        cyl([0.0, -0.29, -0.02], Vec3::Y, 0.22, 0.04, steel()),
        cyl([0.0, -0.3125, -0.02], Vec3::Y, 0.16, 0.005, glass()),
        bx([0.17, -0.33, -0.08], [0.21, -0.31, 0.04], dark_plastic()),
    ];
    obj(
        "washer",
        vec![part("body", body), part("door", d)],
        vec![revolute(1, Vec3::Z, [-0.24, -0.27, 0.0], [0.0, -60.0])],
        ViewHint::default(),
    )
}

/// Storage: a cabinet with one drawer sliding out 0 -> 0.35.
pub fn storage() -> ArticulatedObject {
    let mut body = open_front_shell([-0.35, -0.25, -0.4], [0.35, 0.25, 0.4], 0.03, oak());
    body.push(bx([-0.32, -0.25, 0.085], [0.32, 0.22, 0.115], oak()));
    body.push(bx([-0.34, -0.27, -0.385], [0.34, -0.25, 0.095], walnut()));
    body.extend(handle_x([0.0, -0.27, 0.0], 0.2, steel()));
    let mut d = drawer([-0.335, 0.335], [0.12, 0.385], -0.25, 0.45, walnut(), pale_wood());
    d.push(bx([-0.2, -0.1, 0.142], [-0.02, 0.1, 0.2], red()));
    d.push(cyl([0.12, 0.05, 0.17], Vec3::Z, 0.06, 0.05, blue()));
    obj(
        "storage",
        vec![part("body", body), part("drawer", d)],
        vec![prismatic(1, Vec3::NEG_Y, [0.0, 0.35])],
        ViewHint::default(),
    )
}

/// Scissors lying flat: one blade revolves about the pivot, 45 -> -45 deg.
pub fn scissors() -> ArticulatedObject {
    let t = 0.02;
    let base = vec![
        prism(&[[-0.04, -0.045], [0.5, -0.006], [0.5, 0.008], [-0.04, 0.03]], t, [0.0, 0.0, -0.5 * t], steel()),
        bx([-0.3, -0.075, -t], [-0.04, -0.035, 0.0], red()),
        cyl([-0.36, -0.08, -0.5 * t], Vec3::Z, 0.08, t, red()),
        cyl([0.0, 0.0, 0.0], Vec3::Z, 0.022, 2.0 * t + 0.01, dark_plastic()),
    ];
    let moving = vec![
        prism(&[[-0.04, -0.03], [0.5, -0.008], [0.5, 0.006], [-0.04, 0.045]], t, [0.0, 0.0, 0.5 * t], steel()),
        bx([-0.3, 0.035, 0.0], [-0.04, 0.075, t], blue()),
        cyl([-0.36, 0.08, 0.5 * t], Vec3::Z, 0.08, t, blue()),
    ];
    obj(
        "scissors",
        vec![part("blade_a", base), part("blade_b", moving)],
        vec![revolute(1, Vec3::Z, [0.0, 0.0, 0.0], [45.0, -45.0])],
        ViewHint { front_azimuth_deg: -90.0, motion_elevation_deg: 55.0, distance: 2.3 },
    )
}

/// A utility knife: the blade slides out of the handle along +x, 0 -> 0.3.
pub fn blade() -> ArticulatedObject {
    let o = orange();
    let handle = vec![
        bx([-0.45, -0.06, 0.015], [0.25, 0.06, 0.04], o),
        bx([-0.45, -0.06, -0.04], [0.25, 0.06, -0.015], o),
        bx([-0.45, -0.06, -0.015], [0.25, -0.045, 0.015], dark_plastic()),
        bx([-0.45, 0.045, -0.015], [0.25, 0.06, 0.015], dark_plastic()),
        bx([-0.45, -0.045, -0.015], [-0.43, 0.045, 0.015], dark_plastic()),
        bx([-0.3, -0.05, 0.04], [-0.1, 0.05, 0.045], dark_plastic()),
    ];
    let knife = vec![
        prism(&[[-0.2, -0.04], [0.2, -0.04], [0.24, 0.0], [0.17, 0.04], [-0.2, 0.04]], 0.006, [0.0, 0.0, 0.0], steel()),
        bx([-0.08, -0.015, 0.045], [-0.03, 0.015, 0.065], red()),
    ];
    obj(
        "blade",
        vec![part("handle", handle), part("blade", knife)],
        vec![prismatic(1, Vec3::X, [0.0, 0.3])],
        ViewHint { front_azimuth_deg: -90.0, motion_elevation_deg: 50.0, distance: 2.4 },
    )
}

/// A swivel USB drive: the metal cover revolves about +z, 0 -> -90 deg.
pub fn usb() -> ArticulatedObject {
    let body = vec![
        bx([-0.3, -0.1, -0.04], [0.2, 0.1, 0.04], blue()),
        bx([0.2, -0.06, -0.02], [0.38, 0.06, 0.02], steel()),
        bx([0.25, -0.04, 0.0], [0.35, 0.04, 0.021], dark_plastic()),
    ];
    let cover = vec![
        bx([-0.3, -0.105, 0.04], [0.42, 0.105, 0.05], steel()),
        bx([-0.3, -0.105, -0.05], [0.42, 0.105, -0.04], steel()),
        bx([0.42, -0.105, -0.05], [0.43, 0.105, 0.05], steel()),
        cyl([-0.25, 0.0, 0.0], Vec3::Z, 0.03, 0.11, red()),
    ];
    obj(
        "usb",
        vec![part("body", body), part("cover", cover)],
        vec![revolute(1, Vec3::Z, [-0.25, 0.0, 0.0], [0.0, -90.0])],
        ViewHint { front_azimuth_deg: -90.0, motion_elevation_deg: 50.0, distance: 2.4 },
    )
}

/// Storage with a revolute door (upper) and a prismatic drawer (lower).
pub fn storage_door_drawer() -> ArticulatedObject {
    let mut body = open_front_shell([-0.35, -0.25, -0.45], [0.35, 0.25, 0.45], 0.03, walnut());
    body.push(bx([-0.32, -0.25, -0.1], [0.32, 0.22, -0.07], walnut()));
    body.push(bx([-0.32, -0.2, 0.15], [0.32, 0.22, 0.17], pale_wood()));
    body.extend(shelf_items(-0.28, 0.28, 0.05, 0.17, 2));
    body.extend(shelf_items(-0.28, 0.28, 0.05, -0.07, 5));
    let d = door([-0.345, 0.345], [-0.065, 0.42], -0.25, 0.02, oak(), 0.29);
    let dr = drawer([-0.345, 0.345], [-0.42, -0.105], -0.25, 0.45, oak(), pale_wood());
    obj(
        "storage_door_drawer",
        vec![part("body", body), part("door", d), part("drawer", dr)],
        vec![revolute(1, Vec3::NEG_Z, [-0.35, -0.27, 0.0], [0.0, 90.0]), prismatic(2, Vec3::NEG_Y, [0.0, 0.35])],
        ViewHint::default(),
    )
}

/// Fridge with French doors: left 0 -> -160 deg about +z, right 0 -> -90 deg about -z.
pub fn fridge_two_doors() -> ArticulatedObject {
    let mut body = open_front_shell([-0.4, -0.25, -0.5], [0.4, 0.3, 0.5], 0.03, enamel());
    body.push(bx([-0.37, 0.255, -0.47], [0.37, 0.27, 0.47], liner()));
    for (k, z) in [-0.2f32, 0.1].into_iter().enumerate() {
        body.push(bx([-0.37, -0.15, z - 0.015], [0.37, 0.255, z], glass()));
        body.extend(shelf_items(-0.34, 0.34, 0.1, z, k * 3));
    }
    body.push(bx([-0.37, -0.15, 0.285], [0.37, 0.255, 0.3], glass()));
    body.extend(shelf_items(-0.34, 0.34, 0.1, 0.3, 4));
    body.extend(shelf_items(-0.34, 0.34, 0.1, -0.47, 1));
    let mut l = door([-0.4, -0.003], [-0.5, 0.5], -0.25, 0.05, enamel(), -0.05);
    l.push(bx([-0.37, -0.25, -0.45], [-0.03, -0.245, 0.45], liner()));
    let mut r = door([0.003, 0.4], [-0.5, 0.5], -0.25, 0.05, enamel(), 0.05);
    r.push(bx([0.03, -0.25, -0.45], [0.37, -0.245, 0.45], liner()));
    for z in [-0.3, 0.05] {
        r.push(bx([0.06, -0.245, z], [0.34, -0.19, z + 0.07], orange()));
        l.push(bx([-0.34, -0.245, z], [-0.06, -0.19, z + 0.07], green()));
    }
    obj(
        "fridge_two_doors",
        vec![part("body", body), part("left_door", l), part("right_door", r)],
        vec![
            revolute(1, Vec3::Z, [-0.4, -0.3, 0.0], [0.0, -160.0]),
            revolute(2, Vec3::NEG_Z, [0.4, -0.3, 0.0], [0.0, -90.0]),
        ],
        ViewHint { distance: 3.0, ..ViewHint::default() },
    )
}

/// Storage with four doors (two rows) and two drawers (top row), mixed axis signs.
pub fn storage_complex() -> ArticulatedObject {
    let mut body = open_front_shell([-0.5, -0.25, -0.45], [0.5, 0.25, 0.45], 0.03, oak());
    body.push(bx([-0.47, -0.25, 0.22], [0.47, 0.22, 0.25], oak()));
    body.push(bx([-0.47, -0.25, -0.08], [0.47, 0.22, -0.05], oak()));
    body.push(bx([-0.015, -0.25, -0.42], [0.015, 0.22, 0.22], oak()));
    body.extend(shelf_items(-0.45, -0.05, 0.0, -0.05, 0));
    body.extend(shelf_items(0.05, 0.45, 0.0, -0.05, 3));
    body.extend(shelf_items(-0.45, -0.05, 0.0, -0.42, 2));
    body.extend(shelf_items(0.05, 0.45, 0.0, -0.42, 5));
    let f = walnut();
    let ml = door([-0.495, -0.018], [-0.045, 0.215], -0.25, 0.02, f, -0.07);
    let mr = door([0.018, 0.495], [-0.045, 0.215], -0.25, 0.02, f, 0.07);
    let bl = door([-0.495, -0.018], [-0.415, -0.085], -0.25, 0.02, f, -0.07);
    let br = door([0.018, 0.495], [-0.415, -0.085], -0.25, 0.02, f, 0.07);
    let dl = drawer([-0.495, -0.005], [0.255, 0.42], -0.25, 0.42, f, pale_wood());
    let dr = drawer([0.005, 0.495], [0.255, 0.42], -0.25, 0.42, f, pale_wood());
    obj(
        "storage_complex",
        vec![
            part("body", body),
            part("door_middle_left", ml),
            part("door_middle_right", mr),
            part("door_bottom_left", bl),
            part("door_bottom_right", br),
            part("drawer_left", dl),
            part("drawer_right", dr),
        ],
        vec![
            revolute(1, Vec3::NEG_Z, [-0.5, -0.27, 0.0], [0.0, 120.0]),
            revolute(2, Vec3::NEG_Z, [0.5, -0.27, 0.0], [0.0, -120.0]),
            revolute(3, Vec3::Z, [-0.5, -0.27, 0.0], [0.0, -60.0]),
            revolute(4, Vec3::Z, [0.5, -0.27, 0.0], [0.0, 60.0]),
            prismatic(5, Vec3::NEG_Y, [0.0, 0.1]),
            prismatic(6, Vec3::Y, [0.0, -0.16]),
        ],
        ViewHint { distance: 3.0, ..ViewHint::default() },
    )
}

/// Table (desk) with two stacked drawers (one opening, one closing) and two doors.
pub fn table_complex() -> ArticulatedObject {
    let mut body = vec![bx([-0.5, -0.28, 0.33], [0.5, 0.28, 0.37], walnut())];
    body.extend(open_front_shell([-0.48, -0.24, -0.37], [0.48, 0.26, 0.33], 0.025, cream()));
    body.push(bx([-0.015, -0.24, -0.345], [0.015, 0.235, 0.305], cream()));
    body.push(bx([-0.455, -0.24, -0.03], [-0.015, 0.235, -0.005], cream()));
    body.push(bx([0.015, -0.2, -0.03], [0.455, 0.235, -0.005], cream()));
    body.extend(shelf_items(0.04, 0.44, 0.02, -0.005, 1));
    body.extend(shelf_items(0.04, 0.44, 0.02, -0.345, 4));
    let top = drawer([-0.475, -0.018], [0.0, 0.3], -0.24, 0.45, walnut(), pale_wood());
    let mut bottom = drawer([-0.475, -0.018], [-0.34, -0.035], -0.24, 0.45, walnut(), pale_wood());
    bottom.push(bx([-0.4, -0.15, -0.32], [-0.25, 0.05, -0.26], green()));
    let dl = door([0.018, 0.245], [-0.34, 0.3], -0.24, 0.02, walnut(), 0.21);
    let dr = door([0.251, 0.478], [-0.34, 0.3], -0.24, 0.02, walnut(), 0.29);
    obj(
        "table_complex",
        vec![
            part("body", body),
            part("drawer_top", top),
            part("drawer_bottom", bottom),
            part("door_left", dl),
            part("door_right", dr),
        ],
        vec![
            prismatic(1, Vec3::NEG_Y, [0.0, 0.38]),
            prismatic(2, Vec3::NEG_Y, [0.35, 0.0]),
            revolute(3, Vec3::Z, [0.015, -0.26, 0.0], [0.0, -90.0]),
            revolute(4, Vec3::Z, [0.48, -0.26, 0.0], [0.0, 90.0]),
        ],
        ViewHint { distance: 2.9, ..ViewHint::default() },
    )
}

// ---------------------------------------------------------------- held-out objects

/// Microwave: a painted box, the door hinged on the left, 0 -> 100 deg about -z; a
/// dark window, a control panel on the right, a turntable inside.
pub fn microwave() -> ArticulatedObject {
    let (white, grey, dark) = (paint(0.88, 0.88, 0.86), paint(0.55, 0.56, 0.58), paint(0.12, 0.13, 0.15));
    let mut body = open_front_shell([-0.4, -0.22, -0.25], [0.14, 0.22, 0.25], 0.02, grey);
    body.push(bx([0.14, -0.22, -0.25], [0.4, 0.22, 0.25], white));
    body.push(bx([0.18, -0.225, -0.2], [0.36, -0.22, 0.2], dark));
    for z in [0.12, 0.04, -0.04] {
        body.push(cyl([0.27, -0.235, z], Vec3::Y, 0.025, 0.02, white));
    }
    body.push(cyl([-0.13, 0.0, -0.225], Vec3::Z, 0.16, 0.01, paint(0.75, 0.8, 0.82)));
    body.push(bx([-0.2, -0.05, -0.22], [-0.05, 0.08, -0.14], paint(0.85, 0.35, 0.2)));
    let door = vec![
        bx([-0.4, -0.25, -0.25], [0.14, -0.22, 0.25], white),
        bx([-0.35, -0.255, -0.19], [0.04, -0.25, 0.19], dark),
        bx([0.07, -0.27, -0.15], [0.1, -0.25, 0.15], grey),
    ];
    obj(
        "microwave",
        vec![part("body", body), part("door", door)],
        vec![revolute(1, Vec3::NEG_Z, [-0.4, -0.25, 0.0], [0.0, 100.0])],
        ViewHint::default(),
    )
}

/// Toy chest: an open-topped painted box, the lid hinged along its back edge,
/// lifted 0 -> 75 deg about -x; toys inside.
pub fn chest() -> ArticulatedObject {
    let (blue, cream, floor) = (paint(0.3, 0.45, 0.7), paint(0.92, 0.88, 0.78), paint(0.65, 0.5, 0.35));
    let w = 0.03;
    let mut body = vec![
        bx([-0.4, -0.25, -0.3], [0.4, 0.25, -0.3 + w], floor),
        bx([-0.4, -0.25, -0.3 + w], [0.4, -0.25 + w, 0.2], blue),
        bx([-0.4, 0.25 - w, -0.3 + w], [0.4, 0.25, 0.2], blue),
        bx([-0.4, -0.25 + w, -0.3 + w], [-0.4 + w, 0.25 - w, 0.2], blue),
        bx([0.4 - w, -0.25 + w, -0.3 + w], [0.4, 0.25 - w, 0.2], blue),
    ];
    body.extend(shelf_items(-0.33, 0.33, 0.0, -0.3 + w, 2));
    let lid =
        vec![bx([-0.41, -0.26, 0.2], [0.41, 0.26, 0.24], cream), bx([-0.08, -0.28, 0.17], [0.08, -0.26, 0.22], blue)];
    obj(
        "chest",
        vec![part("body", body), part("lid", lid)],
        vec![revolute(1, Vec3::NEG_X, [0.0, 0.26, 0.24], [0.0, 75.0])],
        ViewHint { motion_elevation_deg: 40.0, ..ViewHint::default() },
    )
}

/// Nightstand: a painted cabinet with an open shelf, its one drawer (a knob, no
/// bar) sliding out 0 -> 0.22.
pub fn nightstand() -> ArticulatedObject {
    let (white, sage) = (paint(0.9, 0.9, 0.88), paint(0.62, 0.7, 0.6));
    let mut body = open_front_shell([-0.28, -0.22, -0.38], [0.28, 0.22, 0.38], 0.025, white);
    body.push(bx([-0.255, -0.22, 0.1], [0.255, 0.195, 0.125], white));
    body.push(bx([-0.15, -0.1, -0.355], [0.05, 0.1, -0.2], paint(0.7, 0.3, 0.3)));
    body.push(cyl([0.15, 0.0, -0.355 + 0.06], Vec3::Z, 0.05, 0.12, paint(0.3, 0.35, 0.6)));
    let mut drawer = drawer_box([-0.255, 0.255], [0.13, 0.355], -0.22, 0.38, sage, white);
    drawer.push(cyl([0.0, -0.255, 0.24], Vec3::Y, 0.02, 0.03, paint(0.75, 0.6, 0.3)));
    obj(
        "nightstand",
        vec![part("body", body), part("drawer", drawer)],
        vec![prismatic(1, Vec3::NEG_Y, [0.0, 0.22])],
        ViewHint::default(),
    )
}

/// Laptop: the screen, hinged along the base's back edge, closes from 110 to 40
/// deg about -x (modelled shut, lying on the base). Two plain slabs, one colour
/// each: a keyboard or a screen as thin slabs on their faces would hide ground-truth
/// faces a few millimetres under others, which the dataset's depth test reads as
/// depth error.
pub fn laptop() -> ArticulatedObject {
    let base = vec![bx([-0.35, -0.24, -0.025], [0.35, 0.24, 0.0], paint(0.25, 0.26, 0.29))];
    let lid = vec![bx([-0.35, -0.24, 0.001], [0.35, 0.24, 0.018], paint(0.7, 0.71, 0.73))];
    obj(
        "laptop",
        vec![part("base", base), part("screen", lid)],
        vec![revolute(1, Vec3::NEG_X, [0.0, 0.24, 0.01], [110.0, 40.0])],
        ViewHint { motion_elevation_deg: 35.0, distance: 2.3, ..ViewHint::default() },
    )
}

/// Dishwasher: a painted body with a fixed control strip along the top; its door,
/// hinged along its bottom front edge, falls open 0 -> 80 deg about +x; two racks
/// of plates and cups inside.
pub fn dishwasher() -> ArticulatedObject {
    let (white, grey, dark) = (paint(0.9, 0.9, 0.9), paint(0.6, 0.62, 0.64), paint(0.2, 0.22, 0.25));
    let mut body = open_front_shell([-0.3, -0.3, -0.42], [0.3, 0.3, 0.42], 0.02, grey);
    body.push(bx([-0.3, -0.33, 0.34], [0.3, -0.3, 0.42], white));
    body.push(bx([0.12, -0.335, 0.36], [0.26, -0.33, 0.4], dark));
    for (z, colour) in [(-0.3, paint(0.35, 0.55, 0.75)), (0.05, paint(0.8, 0.45, 0.3))] {
        body.push(bx([-0.26, -0.26, z], [0.26, 0.26, z + 0.015], paint(0.7, 0.72, 0.75)));
        for k in 0..4 {
            let x = -0.2 + 0.13 * k as f32;
            body.push(cyl([x, 0.0, z + 0.1], Vec3::X, 0.09, 0.015, colour));
        }
    }
    let door =
        vec![bx([-0.3, -0.33, -0.42], [0.3, -0.3, 0.34], white), bx([-0.15, -0.35, 0.27], [0.15, -0.33, 0.3], dark)];
    obj(
        "dishwasher",
        vec![part("body", body), part("door", door)],
        vec![revolute(1, Vec3::X, [0.0, -0.33, -0.42], [0.0, 80.0])],
        ViewHint { motion_elevation_deg: 35.0, ..ViewHint::default() },
    )
}

/// Sideboard: a low painted cabinet with two sliding doors in two tracks; the
/// front door slides 0 -> 0.42 along +x in front of the fixed one, opening the
/// left compartment (a vase and boxes inside).
pub fn sideboard() -> ArticulatedObject {
    let (cream, olive) = (paint(0.9, 0.86, 0.76), paint(0.5, 0.55, 0.35));
    let mut body = open_front_shell([-0.5, -0.2, -0.3], [0.5, 0.2, 0.3], 0.025, cream);
    body.push(bx([-0.01, -0.2, -0.275], [0.01, 0.175, 0.275], cream));
    body.push(bx([0.0, -0.22, -0.27], [0.475, -0.2, 0.27], olive));
    body.push(cyl([-0.3, 0.0, -0.155], Vec3::Z, 0.06, 0.24, paint(0.3, 0.45, 0.7)));
    body.push(bx([-0.2, -0.1, -0.275], [-0.06, 0.1, -0.15], paint(0.75, 0.3, 0.25)));
    let door = vec![
        bx([-0.475, -0.245, -0.27], [0.0, -0.225, 0.27], olive),
        bx([-0.07, -0.25, -0.06], [-0.04, -0.245, 0.06], paint(0.25, 0.22, 0.2)),
    ];
    obj(
        "sideboard",
        vec![part("body", body), part("door", door)],
        vec![prismatic(1, Vec3::X, [0.0, 0.42])],
        ViewHint::default(),
    )
}

/// Wall cabinet: a painted cabinet with a shelf; its flap door, hinged along the
/// top front edge, lifts 0 -> 75 deg about -x (the bottom swings out and up).
pub fn wall_cabinet() -> ArticulatedObject {
    let (white, teal) = (paint(0.92, 0.92, 0.9), paint(0.3, 0.55, 0.55));
    let mut body = open_front_shell([-0.4, -0.18, -0.25], [0.4, 0.18, 0.25], 0.02, white);
    body.push(bx([-0.38, -0.18, -0.01], [0.38, 0.16, 0.01], white));
    body.push(cyl([-0.2, 0.0, 0.07], Vec3::Z, 0.04, 0.12, paint(0.8, 0.7, 0.3)));
    body.push(bx([0.05, -0.08, -0.23], [0.3, 0.1, -0.1], paint(0.6, 0.3, 0.5)));
    let door = vec![
        bx([-0.4, -0.2, -0.25], [0.4, -0.18, 0.25], teal),
        bx([-0.12, -0.22, -0.23], [0.12, -0.2, -0.21], paint(0.85, 0.85, 0.85)),
    ];
    obj(
        "wall_cabinet",
        vec![part("body", body), part("door", door)],
        vec![revolute(1, Vec3::NEG_X, [0.0, -0.2, 0.25], [0.0, 75.0])],
        ViewHint { motion_elevation_deg: 15.0, ..ViewHint::default() },
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_object_builds_with_consistent_joints() {
        for name in OBJECT_NAMES.into_iter().chain(HELD_OUT_NAMES) {
            let o = object(name).unwrap();
            assert_eq!(o.name, name);
            assert_eq!(o.joints.len(), o.parts.len() - 1, "{name}");
            for (k, j) in o.joints.iter().enumerate() {
                assert_eq!(j.part, k + 1);
                assert!((j.axis.length() - 1.0).abs() < 1e-6);
            }
            // About one unit across, near the origin, at both ends of the motion.
            for t in [0.0, 1.0] {
                let b = o.posed(t).bounds();
                assert!(b.extent().max_element() < 1.9, "{name} at t={t}: {b:?}");
                assert!(b.center().length() < 0.6, "{name} at t={t}: {b:?}");
            }
            let b0 = o.posed(0.0).bounds();
            assert!(b0.extent().max_element() > 0.5, "{name}: {b0:?}");
        }
        assert!(object("toaster").unwrap_err().to_string().contains("fridge, oven"));
    }
}
