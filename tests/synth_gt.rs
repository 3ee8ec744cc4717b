//! Exact-geometry checks of the synthetic benchmark, on the files as written: GT meshes
//! projected with the written poses land on pixels of their part at their depth, and
//! GT meshes moved by the GT joints rasterise to the rendered part masks.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use aim::camera::Camera;
use aim::mesh::read_obj;
use aim::mesh::MeshData;
use aim::synth::gt::JointsFile;
use aim::synth::{object, write_dataset, SynthConfig, HELD_OUT_NAMES, OBJECT_NAMES};
use aim_capture::dataset::{load_aim, LoadOptions};
use aim_capture::Frame;
use glam::{Affine3A, Vec3};

const RES: u32 = 160;

fn config() -> SynthConfig {
    SynthConfig {
        resolution: RES,
        scan_views: 6,
        motion_frames: 21,
        end_views: 4,
        test_views: 2,
        motion_test_every: 5,
        samples_per_pixel: 1,
        seed: 3,
        ..SynthConfig::default()
    }
}

/// The benchmark's objects and those held out of it.
fn all_objects() -> impl Iterator<Item = &'static str> {
    OBJECT_NAMES.into_iter().chain(HELD_OUT_NAMES)
}

/// All objects written once per test binary.
fn datasets() -> &'static PathBuf {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let root = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("synth_gt");
        for name in all_objects() {
            write_dataset(&object(name).unwrap(), &root.join(name), &config(), &|_, _| {}).unwrap();
        }
        root
    })
}

struct Gt {
    joints: JointsFile,
    start: Vec<MeshData>,
}

fn load_gt(dir: &Path) -> Gt {
    let joints = JointsFile::load(&dir.join("gt/joints.json")).unwrap();
    let start =
        joints.parts.iter().map(|p| read_obj(&dir.join("gt").join(p.mesh_start.as_ref().unwrap())).unwrap()).collect();
    Gt { joints, start }
}

/// Motion of part `k` from the start state to time `t`, from the GT joints only.
fn gt_motion(gt: &Gt, k: usize, t: f32) -> Affine3A {
    gt.joints.joints.iter().find(|j| j.part == k).map(|j| j.motion_from_start(t)).unwrap_or(Affine3A::IDENTITY)
}

fn frame_time(f: &Frame) -> f32 {
    match f.phase {
        aim_capture::Phase::Scan => 0.0,
        aim_capture::Phase::After => 1.0,
        aim_capture::Phase::Motion => f.motion_time.expect("motion frames carry time"),
    }
}

fn part_image(f: &Frame) -> image::GrayImage {
    let p = f.source.strip_suffix(".png").unwrap().to_string() + "_part.png";
    image::open(&p).unwrap().into_luma8()
}

fn all_frames(dir: &Path) -> Vec<Frame> {
    let ds = load_aim(dir, &LoadOptions { depth: true }).unwrap();
    let end = ds.end.expect("end/ written");
    [ds.start.train, ds.start.test, ds.motion.train, ds.motion.test, end.train, end.test].concat()
}

#[test]
fn projected_gt_surface_points_hit_their_part_at_their_depth() {
    let root = datasets();
    for name in all_objects() {
        let dir = root.join(name);
        let gt = load_gt(&dir);
        let samples: Vec<Vec<Vec3>> =
            gt.start.iter().enumerate().map(|(k, m)| m.sample_surface(3000, 11 + k as u64)).collect();
        let (mut in_image, mut visible, mut id_ok) = (0usize, 0usize, 0usize);
        let mut depth_err = Vec::new();
        for f in all_frames(&dir) {
            let cam = Camera::new(f.intrinsics, f.world_to_camera);
            let ids = part_image(&f);
            let depth = f.depth.as_ref().expect("depth written");
            let t = frame_time(&f);
            for (k, pts) in samples.iter().enumerate() {
                let m = gt_motion(&gt, k, t);
                for p in pts {
                    let Some((u, v, z)) = cam.project(m.transform_point3(*p)) else { continue };
                    if !(u >= 0.0 && v >= 0.0 && u < RES as f32 && v < RES as f32) {
                        continue;
                    }
                    in_image += 1;
                    // Inverse depth is affine in (u, v) on a plane, so bilinear
                    // interpolation of 1/depth between the four surrounding pixel centres
                    // reproduces a visible planar surface's depth exactly.
                    let (x0, y0) = ((u - 0.5).floor(), (v - 0.5).floor());
                    if !(x0 >= 0.0 && y0 >= 0.0 && x0 + 1.0 < RES as f32 && y0 + 1.0 < RES as f32) {
                        continue;
                    }
                    let (fx, fy) = (u - 0.5 - x0, v - 0.5 - y0);
                    let at = |dx: u32, dy: u32| {
                        let (x, y) = (x0 as u32 + dx, y0 as u32 + dy);
                        (depth[(y * RES + x) as usize], ids.get_pixel(x, y)[0] as usize)
                    };
                    let q = [at(0, 0), at(1, 0), at(0, 1), at(1, 1)];
                    if q.iter().any(|&(d, _)| d <= 0.0) {
                        continue;
                    }
                    let inv =
                        (1.0 - fy) * ((1.0 - fx) / q[0].0 + fx / q[1].0) + fy * ((1.0 - fx) / q[2].0 + fx / q[3].0);
                    let err = (1.0 / inv - z).abs();
                    // Visible: the rendered surface there is at this point's depth (2 mm:
                    // millimetre quantisation plus interpolation across a crease).
                    if err < 0.002 {
                        visible += 1;
                        if ids.get_pixel(u as u32, v as u32)[0] as usize == k {
                            id_ok += 1;
                        }
                    }
                    // Depth precision where the four pixels see this part's (locally visible) surface.
                    if err < 0.01 && q.iter().all(|&(_, id)| id == k) {
                        depth_err.push(err);
                    }
                }
            }
        }
        depth_err.sort_by(f32::total_cmp);
        let median = depth_err[depth_err.len() / 2];
        let vis_frac = visible as f64 / in_image as f64;
        let id_frac = id_ok as f64 / visible as f64;
        println!(
            "{name}: {in_image} in image, visible {vis_frac:.3}, part id agrees {id_frac:.4}, median |dz| {median:.5}"
        );
        assert!(vis_frac > 0.12, "{name}: only {vis_frac:.3} of projected GT points are at the rendered depth");
        assert!(id_frac > 0.985, "{name}: part id agrees for only {id_frac:.4} of visible GT points");
        assert!(median < 0.0005, "{name}: median depth error {median} m");
    }
}

/// Z-buffer rasterisation of world-space meshes (one per part id) at pixel centres.
fn rasterise_part_ids(meshes: &[MeshData], cam: &Camera) -> Vec<u8> {
    let (w, h) = (cam.width() as usize, cam.height() as usize);
    let mut zbuf = vec![f32::INFINITY; w * h];
    let mut ids = vec![255u8; w * h];
    for (k, m) in meshes.iter().enumerate() {
        for tri in &m.triangles {
            let p: Vec<(f32, f32, f32)> = tri.iter().filter_map(|&i| cam.project(m.vertices[i as usize])).collect();
            if p.len() < 3 {
                continue;
            }
            let (a, b, c) = (p[0], p[1], p[2]);
            let area = (b.0 - a.0) * (c.1 - a.1) - (b.1 - a.1) * (c.0 - a.0);
            if area.abs() < 1e-12 {
                continue;
            }
            let x0 = (a.0.min(b.0).min(c.0) - 0.5).floor().max(0.0) as usize;
            let x1 = ((a.0.max(b.0).max(c.0) - 0.5).ceil().max(0.0) as usize).min(w - 1);
            let y0 = (a.1.min(b.1).min(c.1) - 0.5).floor().max(0.0) as usize;
            let y1 = ((a.1.max(b.1).max(c.1) - 0.5).ceil().max(0.0) as usize).min(h - 1);
            for y in y0..=y1 {
                for x in x0..=x1 {
                    let (px, py) = (x as f32 + 0.5, y as f32 + 0.5);
                    let w0 = ((b.0 - px) * (c.1 - py) - (b.1 - py) * (c.0 - px)) / area;
                    let w1 = ((c.0 - px) * (a.1 - py) - (c.1 - py) * (a.0 - px)) / area;
                    let w2 = 1.0 - w0 - w1;
                    if w0 < 0.0 || w1 < 0.0 || w2 < 0.0 {
                        continue;
                    }
                    let z = 1.0 / (w0 / a.2 + w1 / b.2 + w2 / c.2);
                    let o = y * w + x;
                    if z < zbuf[o] {
                        zbuf[o] = z;
                        ids[o] = k as u8;
                    }
                }
            }
        }
    }
    ids
}

#[test]
fn parts_moved_by_gt_joints_match_rendered_masks() {
    let root = datasets();
    for name in all_objects() {
        let dir = root.join(name);
        let gt = load_gt(&dir);
        let mut worst = 1.0f64;
        let mut checked = 0;
        for f in all_frames(&dir) {
            if f.phase == aim_capture::Phase::Scan {
                continue;
            }
            let t = frame_time(&f);
            let cam = Camera::new(f.intrinsics, f.world_to_camera);
            let moved: Vec<MeshData> =
                gt.start.iter().enumerate().map(|(k, m)| m.transformed(&gt_motion(&gt, k, t))).collect();
            let raster = rasterise_part_ids(&moved, &cam);
            let rendered = part_image(&f).into_raw();
            for k in 0..moved.len() {
                let a: Vec<bool> = raster.iter().map(|&v| v as usize == k).collect();
                let b: Vec<bool> = rendered.iter().map(|&v| v as usize == k).collect();
                let inter = a.iter().zip(&b).filter(|(x, y)| **x && **y).count();
                let union = a.iter().zip(&b).filter(|(x, y)| **x || **y).count();
                // Parts covering only a handful of pixels (a drawer front seen edge-on)
                // have IoU dominated by boundary pixels; require a real mask.
                if union < 300 {
                    continue;
                }
                let iou = inter as f64 / union as f64;
                checked += 1;
                assert!(iou > 0.98, "{name} {} part {k} at t={t}: IoU {iou:.4}", f.source);
                worst = worst.min(iou);
            }
        }
        println!("{name}: {checked} part masks, worst IoU {worst:.4}");
        assert!(checked >= 20, "{name}: only {checked} masks were large enough to check");
    }
}

#[test]
fn gt_end_meshes_equal_start_meshes_moved_by_the_joints() {
    let root = datasets();
    for name in all_objects() {
        let dir = root.join(name);
        let gt = load_gt(&dir);
        let mut moving = 0;
        for (k, p) in gt.joints.parts.iter().enumerate() {
            let end = read_obj(&dir.join("gt").join(p.mesh_end.as_ref().unwrap())).unwrap();
            let moved = gt.start[k].transformed(&gt_motion(&gt, k, 1.0));
            assert_eq!(end.triangles, moved.triangles);
            let err = end.vertices.iter().zip(&moved.vertices).map(|(a, b)| a.distance(*b)).fold(0.0f32, f32::max);
            assert!(err < 1e-4, "{name} part {k}: end mesh differs from the moved start mesh by {err}");
            let shift =
                end.vertices.iter().zip(&gt.start[k].vertices).map(|(a, b)| a.distance(*b)).fold(0.0f32, f32::max);
            if k > 0 {
                assert!(shift > 0.05, "{name} part {k} barely moves ({shift})");
                moving += 1;
            } else {
                assert_eq!(shift, 0.0, "{name}: the base moved");
            }
        }
        assert_eq!(moving, gt.joints.joints.len());
    }
}
