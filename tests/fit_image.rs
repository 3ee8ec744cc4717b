//! Fitting: from a random start, optimise a Gaussian set against a target image
//! with the rasterizer's gradients, the 3DGS loss and Adam; it must reach > 30 dB.

use glam::{Mat4, Vec3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use aim::camera::{Camera, Intrinsics};
use aim::render::{backward, render, RenderOptions};
use aim::splat::{logit, GaussianSet};
use aim::train::loss::{loss_and_grad, psnr};
use aim::train::optim::{Adam, LearningRates};

/// A smooth target with edges and colour variation: two overlapping discs on a gradient.
fn target(w: u32, h: u32) -> Vec<f32> {
    let mut img = Vec::with_capacity((3 * w * h) as usize);
    for y in 0..h {
        for x in 0..w {
            let (u, v) = ((x as f32 + 0.5) / w as f32, (y as f32 + 0.5) / h as f32);
            let mut c = Vec3::new(0.2 + 0.6 * u, 0.3 + 0.4 * v, 0.5);
            if (u - 0.35).powi(2) + (v - 0.4).powi(2) < 0.04 {
                c = Vec3::new(0.9, 0.2, 0.1);
            }
            if (u - 0.65).powi(2) + (v - 0.6).powi(2) < 0.03 {
                c = c * 0.3 + Vec3::new(0.1, 0.6, 0.2);
            }
            img.extend_from_slice(&c.to_array());
        }
    }
    img
}

#[test]
fn fitting_a_target_image_reaches_30_db() {
    let (w, h) = (64u32, 64u32);
    let cam = Camera::new(Intrinsics::from_fov_x(w, h, 1.0), Mat4::IDENTITY);
    let tgt = target(w, h);
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let mut gs = GaussianSet::new(0);
    let half = (0.5f32).tan() * 2.0; // half-width of the view at depth 2
    for _ in 0..2000 {
        let mean = Vec3::new(rng.random_range(-half..half), rng.random_range(-half..half), rng.random_range(1.9..2.1));
        let dc = [rng.random_range(-0.5..0.5), rng.random_range(-0.5..0.5), rng.random_range(-0.5..0.5)];
        gs.push(mean, Vec3::splat((0.03f32).ln()), [1.0, 0.0, 0.0, 0.0], logit(0.5), dc, &[]);
    }
    let mut adam = Adam::new(&gs);
    let lrs = LearningRates {
        means: 2e-3,
        log_scales: 1e-2,
        rotations: 1e-2,
        opacity_logits: 5e-2,
        sh_dc: 2e-2,
        sh_rest: 0.0,
    };
    let opts = RenderOptions::default();
    let mut last_psnr = 0.0;
    for _ in 0..400 {
        let r = render(&gs, &cam, &opts);
        let out = loss_and_grad(&r.image.color, &tgt, w as usize, h as usize, 0.2);
        let g = backward(&gs, &r, &out.grad, None, None);
        adam.step(&mut gs, &g.params, &lrs);
        last_psnr = psnr(&r.image.color, &tgt);
    }
    let final_psnr = psnr(&render(&gs, &cam, &opts).image.color, &tgt);
    eprintln!("fitting: {final_psnr:.2} dB after 400 steps");
    assert!(final_psnr > 30.0, "PSNR after 400 steps: {final_psnr:.2} dB (previous step {last_psnr:.2})");
}
