//! Motion-window detection: when does the hand take hold of the object (hand-in) and
//! let go (hand-out)? Frames before the first hand-in are `Scan`, between a hand-in and
//! its hand-out `Motion`, after a hand-out `After`. A recording may hold several
//! interactions one after another: after a hand-out the next hand-in opens another
//! window, so the events alternate hand-in, hand-out, hand-in, ...
//!
//! Pluggable evidence ([`Evidence`]) gives a per-frame score; a [`WindowTracker`] turns
//! the scores into events with hysteresis in value (on/off thresholds) and in time
//! (a run of `min_on` frames starts the window, `min_off` frames end it). Events are
//! back-dated to the first frame of the deciding run, so the tags are exact at the
//! cost of a latency of `max(min_on, min_off)` frames.
//!
//! Evidence sources: MPS hand tracking (wrist/palm near the object region,
//! confidence-gated), skin colour in the object's image region, explicit timestamps.

use std::collections::VecDeque;

use glam::{DVec3, Mat4, Vec3, Vec4};
use serde::Serialize;

use crate::calib::Se3;
use crate::frame::{Intrinsics, Phase};
use crate::mps::HandTracking;

/// A change of interaction state.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
#[serde(tag = "event", rename_all = "snake_case")]
pub enum MotionEvent {
    HandIn { frame: usize, timestamp_s: f64 },
    HandOut { frame: usize, timestamp_s: f64 },
}

/// Hysteresis settings.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Hysteresis {
    /// Evidence at or above this counts as "hand".
    pub on: f32,
    /// Evidence below this counts as "no hand" (between: keep the current state).
    pub off: f32,
    /// Consecutive "hand" frames needed for hand-in.
    pub min_on: usize,
    /// Consecutive "no hand" frames needed for hand-out.
    pub min_off: usize,
}

impl Default for Hysteresis {
    fn default() -> Self {
        Hysteresis { on: 0.5, off: 0.5, min_on: 3, min_off: 3 }
    }
}

/// Turns per-frame evidence into phases and events. Generic over the item it holds
/// back while a decision is pending (a frame, or just an index).
#[derive(Debug)]
pub struct WindowTracker<T> {
    cfg: Hysteresis,
    state: Phase,
    pending: VecDeque<(T, usize, f64)>,
    pub events: Vec<MotionEvent>,
}

impl<T> WindowTracker<T> {
    pub fn new(cfg: Hysteresis) -> Self {
        WindowTracker { cfg, state: Phase::Scan, pending: VecDeque::new(), events: Vec::new() }
    }

    pub fn phase(&self) -> Phase {
        self.state
    }

    /// Feed one frame; returns the items whose phase is now decided, in order, and any
    /// event that was decided (also appended to `events`).
    pub fn push(
        &mut self,
        item: T,
        frame: usize,
        timestamp_s: f64,
        evidence: f32,
    ) -> (Vec<(T, Phase)>, Option<MotionEvent>) {
        let mut out = Vec::new();
        let mut event = None;
        let hand = evidence >= self.cfg.on;
        let no_hand = evidence < self.cfg.off || !evidence.is_finite();
        match self.state {
            // Before a window (the scan, or after an earlier window): the same test opens one.
            Phase::Scan | Phase::After => {
                if hand {
                    self.pending.push_back((item, frame, timestamp_s));
                    if self.pending.len() >= self.cfg.min_on.max(1) {
                        let (_, f0, t0) = self.pending[0];
                        let e = MotionEvent::HandIn { frame: f0, timestamp_s: t0 };
                        self.events.push(e);
                        event = Some(e);
                        self.state = Phase::Motion;
                        out.extend(self.pending.drain(..).map(|(it, _, _)| (it, Phase::Motion)));
                    }
                } else {
                    let idle = self.state;
                    out.extend(self.pending.drain(..).map(|(it, _, _)| (it, idle)));
                    out.push((item, idle));
                }
            }
            Phase::Motion => {
                if no_hand {
                    self.pending.push_back((item, frame, timestamp_s));
                    if self.pending.len() >= self.cfg.min_off.max(1) {
                        let (_, f0, t0) = self.pending[0];
                        let e = MotionEvent::HandOut { frame: f0, timestamp_s: t0 };
                        self.events.push(e);
                        event = Some(e);
                        self.state = Phase::After;
                        out.extend(self.pending.drain(..).map(|(it, _, _)| (it, Phase::After)));
                    }
                } else {
                    out.extend(self.pending.drain(..).map(|(it, _, _)| (it, Phase::Motion)));
                    out.push((item, Phase::Motion));
                }
            }
        }
        (out, event)
    }

    /// End of stream: release pending items in the current state (an unfinished run
    /// does not change state).
    pub fn flush(&mut self) -> Vec<(T, Phase)> {
        let s = self.state;
        self.pending.drain(..).map(|(it, _, _)| (it, s)).collect()
    }

    /// The first detected window (hand-in, hand-out) in seconds, if any.
    pub fn window(&self) -> (Option<f64>, Option<f64>) {
        window_of(&self.events)
    }
}

/// The first window's (hand-in, hand-out) times from a list of events.
pub fn window_of(events: &[MotionEvent]) -> (Option<f64>, Option<f64>) {
    let hin = events.iter().find_map(|e| match e {
        MotionEvent::HandIn { timestamp_s, .. } => Some(*timestamp_s),
        _ => None,
    });
    let hout = events.iter().find_map(|e| match e {
        MotionEvent::HandOut { timestamp_s, .. } => Some(*timestamp_s),
        _ => None,
    });
    (hin, hout)
}

/// What an evidence source may look at for one frame.
pub struct FrameView<'a> {
    pub index: usize,
    /// Device-clock capture time in ns (the MPS time base).
    pub timestamp_ns: i64,
    /// The undistorted RGBA image.
    pub image: &'a image::RgbaImage,
    pub intrinsics: &'a Intrinsics,
    /// OpenCV world-to-camera, if the frame is posed.
    pub world_to_camera: Option<Mat4>,
    /// T_world_device at the frame time, if known (MPS trajectory).
    pub t_world_device: Option<Se3>,
}

/// A per-frame hand score.
pub trait Evidence: Send {
    fn name(&self) -> &'static str;
    /// Suggested hysteresis for this score.
    fn hysteresis(&self) -> Hysteresis;
    fn evidence(&mut self, f: &FrameView<'_>) -> f32;
}

/// An axis-aligned box in world coordinates where the object is (plus a margin).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, serde::Deserialize)]
pub struct ObjectRegion {
    pub min: [f64; 3],
    pub max: [f64; 3],
}

impl ObjectRegion {
    /// The box with corners x0,y0,z0 and x1,y1,z1 (world coordinates, metres),
    /// each min below its max.
    pub fn from_corners(corners: &[f64]) -> std::result::Result<Self, String> {
        match *corners {
            [x0, y0, z0, x1, y1, z1] if x0 < x1 && y0 < y1 && z0 < z1 => {
                Ok(ObjectRegion { min: [x0, y0, z0], max: [x1, y1, z1] })
            }
            _ => Err(format!(
                "a region is x0,y0,z0,x1,y1,z1 with each min below its max (a box in world coordinates), got {corners:?}"
            )),
        }
    }

    pub fn distance(&self, p: DVec3) -> f64 {
        let lo = DVec3::from_array(self.min);
        let hi = DVec3::from_array(self.max);
        let d = (lo - p).max(p - hi).max(DVec3::ZERO);
        d.length()
    }

    fn corners(&self) -> [Vec3; 8] {
        let mut c = [Vec3::ZERO; 8];
        for (i, v) in c.iter_mut().enumerate() {
            *v = Vec3::new(
                if i & 1 == 0 { self.min[0] } else { self.max[0] } as f32,
                if i & 2 == 0 { self.min[1] } else { self.max[1] } as f32,
                if i & 4 == 0 { self.min[2] } else { self.max[2] } as f32,
            );
        }
        c
    }

    /// The region's bounding rectangle in an image (x0, y0, x1, y1), clamped; None when
    /// the box is entirely behind the camera or off-image.
    pub fn image_rect(&self, w2c: &Mat4, k: &Intrinsics) -> Option<(u32, u32, u32, u32)> {
        let mut lo = [f32::INFINITY; 2];
        let mut hi = [f32::NEG_INFINITY; 2];
        let points = self.corners().map(|c| *w2c * Vec4::new(c.x, c.y, c.z, 1.0));
        if points.iter().all(|p| p.z <= 1e-3) {
            return None;
        }
        for p in points {
            if p.z <= 1e-3 {
                // A corner behind the camera: be conservative and take the whole image.
                return Some((0, 0, k.width, k.height));
            }
            let u = k.fx * p.x / p.z + k.cx;
            let v = k.fy * p.y / p.z + k.cy;
            lo = [lo[0].min(u), lo[1].min(v)];
            hi = [hi[0].max(u), hi[1].max(v)];
        }
        let x0 = lo[0].floor().clamp(0.0, k.width as f32) as u32;
        let y0 = lo[1].floor().clamp(0.0, k.height as f32) as u32;
        let x1 = hi[0].ceil().clamp(0.0, k.width as f32) as u32;
        let y1 = hi[1].ceil().clamp(0.0, k.height as f32) as u32;
        (x1 > x0 && y1 > y0).then_some((x0, y0, x1, y1))
    }
}

/// MPS hand tracking: 1 when a hand with confidence >= `min_confidence` has its wrist
/// or palm within `margin` of an object region (or anywhere, without regions), else 0.
pub struct HandTrackingEvidence {
    pub hands: HandTracking,
    /// The objects a hand may take hold of (empty: anywhere).
    pub regions: Vec<ObjectRegion>,
    pub margin: f64,
    pub min_confidence: f64,
    /// Largest gap between a frame and the nearest hand sample (ns).
    pub max_gap_ns: i64,
    pub hysteresis: Hysteresis,
}

impl HandTrackingEvidence {
    pub fn new(hands: HandTracking, regions: Vec<ObjectRegion>) -> Self {
        HandTrackingEvidence {
            hands,
            regions,
            margin: 0.05,
            min_confidence: 0.5,
            max_gap_ns: 100_000_000,
            hysteresis: Hysteresis { on: 0.5, off: 0.5, min_on: 2, min_off: 2 },
        }
    }
}

impl Evidence for HandTrackingEvidence {
    fn name(&self) -> &'static str {
        "mps-hands"
    }
    fn hysteresis(&self) -> Hysteresis {
        self.hysteresis
    }
    fn evidence(&mut self, f: &FrameView<'_>) -> f32 {
        let Some(s) = self.hands.nearest(f.timestamp_ns, self.max_gap_ns) else { return 0.0 };
        for h in s.hands() {
            if h.confidence < self.min_confidence {
                continue;
            }
            if self.regions.is_empty() {
                return 1.0;
            }
            // With regions but no pose the hand cannot be placed in the world.
            let Some(twd) = &f.t_world_device else { continue };
            let (palm, wrist) = (twd.transform_point(h.palm_device), twd.transform_point(h.wrist_device));
            if self.regions.iter().any(|r| r.distance(palm).min(r.distance(wrist)) <= self.margin) {
                return 1.0;
            }
        }
        0.0
    }
}

/// Skin colour in an object's image region: the fraction of sampled pixels in the
/// region whose YCbCr falls in the usual skin range *and* that connect to skin outside
/// the region (see [`connected_skin_fraction`]), divided by `reference_fraction`, capped
/// at 1; with several objects, the most of any of them.
pub struct SkinEvidence {
    /// The objects' regions (empty: the central half of the image).
    pub regions: Vec<ObjectRegion>,
    /// Skin fraction that counts as a full "hand" score.
    pub reference_fraction: f32,
    /// Sample every `stride`-th pixel in x and y.
    pub stride: u32,
    pub hysteresis: Hysteresis,
}

impl Default for SkinEvidence {
    fn default() -> Self {
        SkinEvidence {
            regions: Vec::new(),
            reference_fraction: 0.004,
            stride: 2,
            hysteresis: Hysteresis { on: 1.0, off: 0.5, min_on: 3, min_off: 3 },
        }
    }
}

/// The classic YCbCr skin box (Chai & Ngan, widened a little), with a brightness floor.
pub fn is_skin(r: u8, g: u8, b: u8) -> bool {
    let (r, g, b) = (r as f32, g as f32, b as f32);
    let y = 0.299 * r + 0.587 * g + 0.114 * b;
    let cb = 128.0 - 0.168_736 * r - 0.331_264 * g + 0.5 * b;
    let cr = 128.0 + 0.5 * r - 0.418_688 * g - 0.081_312 * b;
    y > 50.0 && (77.0..=127.0).contains(&cb) && (137.0..=175.0).contains(&cr)
}

/// Fraction of skin pixels (alpha > 0) in a rectangle, sampling every `stride` pixels.
pub fn skin_fraction(img: &image::RgbaImage, rect: (u32, u32, u32, u32), stride: u32) -> f32 {
    let (x0, y0, x1, y1) = rect;
    let stride = stride.max(1) as usize;
    let (mut n, mut s) = (0u32, 0u32);
    for y in (y0..y1.min(img.height())).step_by(stride) {
        for x in (x0..x1.min(img.width())).step_by(stride) {
            let p = img.get_pixel(x, y).0;
            if p[3] == 0 {
                continue;
            }
            n += 1;
            if is_skin(p[0], p[1], p[2]) {
                s += 1;
            }
        }
    }
    if n == 0 {
        0.0
    } else {
        s as f32 / n as f32
    }
}

/// Skin evidence that counts only skin connected to skin outside the region: a hand
/// reaches into the object's region from outside (the arm), while skin-coloured things
/// that belong to the object (wood, food in a fridge) sit inside it unconnected.
/// Returns the fraction of sampled region pixels that are such connected skin.
pub fn connected_skin_fraction(img: &image::RgbaImage, rect: (u32, u32, u32, u32), stride: u32) -> f32 {
    let stride = stride.max(1);
    let gw = img.width().div_ceil(stride) as usize;
    let gh = img.height().div_ceil(stride) as usize;
    if gw == 0 || gh == 0 {
        return 0.0;
    }
    let (x0, y0, x1, y1) = rect;
    let inside = |gx: usize, gy: usize| {
        let (x, y) = (gx as u32 * stride, gy as u32 * stride);
        x >= x0 && x < x1 && y >= y0 && y < y1
    };
    let mut skin = vec![false; gw * gh];
    for gy in 0..gh {
        for gx in 0..gw {
            let p = img.get_pixel(gx as u32 * stride, gy as u32 * stride).0;
            skin[gy * gw + gx] = p[3] > 0 && is_skin(p[0], p[1], p[2]);
        }
    }
    // Flood fill (4-connected) from skin cells outside the region.
    let mut seen = vec![false; gw * gh];
    let mut stack: Vec<usize> = Vec::new();
    for gy in 0..gh {
        for gx in 0..gw {
            let i = gy * gw + gx;
            if skin[i] && !inside(gx, gy) {
                seen[i] = true;
                stack.push(i);
            }
        }
    }
    let mut n_in = 0usize;
    while let Some(i) = stack.pop() {
        let (gx, gy) = (i % gw, i / gw);
        if inside(gx, gy) {
            n_in += 1;
        }
        let mut visit = |j: usize| {
            if skin[j] && !seen[j] {
                seen[j] = true;
                stack.push(j);
            }
        };
        if gx > 0 {
            visit(i - 1);
        }
        if gx + 1 < gw {
            visit(i + 1);
        }
        if gy > 0 {
            visit(i - gw);
        }
        if gy + 1 < gh {
            visit(i + gw);
        }
    }
    let n_rect = (0..gh).flat_map(|gy| (0..gw).map(move |gx| (gx, gy))).filter(|&(gx, gy)| inside(gx, gy)).count();
    if n_rect == 0 {
        0.0
    } else {
        n_in as f32 / n_rect as f32
    }
}

impl SkinEvidence {
    /// The evidence for one image and region rectangle.
    pub fn score(&self, img: &image::RgbaImage, rect: (u32, u32, u32, u32)) -> f32 {
        (connected_skin_fraction(img, rect, self.stride) / self.reference_fraction.max(1e-6)).min(1.0)
    }
}

impl Evidence for SkinEvidence {
    fn name(&self) -> &'static str {
        "skin"
    }
    fn hysteresis(&self) -> Hysteresis {
        self.hysteresis
    }
    fn evidence(&mut self, f: &FrameView<'_>) -> f32 {
        let (w, h) = (f.image.width(), f.image.height());
        match (self.regions.is_empty(), &f.world_to_camera) {
            (false, Some(w2c)) => self
                .regions
                .iter()
                .filter_map(|r| r.image_rect(w2c, f.intrinsics))
                .map(|rect| self.score(f.image, rect))
                .fold(0.0, f32::max),
            // No region, or no pose to place it: the central half of the image.
            _ => self.score(f.image, (w / 4, h / 4, 3 * w / 4, 3 * h / 4)),
        }
    }
}

/// Explicit hand-in / hand-out timestamps (seconds on the frames' clock).
pub struct ExplicitEvidence {
    pub hand_in_s: f64,
    pub hand_out_s: f64,
}

impl Evidence for ExplicitEvidence {
    fn name(&self) -> &'static str {
        "explicit"
    }
    fn hysteresis(&self) -> Hysteresis {
        Hysteresis { on: 0.5, off: 0.5, min_on: 1, min_off: 1 }
    }
    fn evidence(&mut self, f: &FrameView<'_>) -> f32 {
        let t = f.timestamp_ns as f64 * 1e-9;
        if t >= self.hand_in_s && t < self.hand_out_s {
            1.0
        } else {
            0.0
        }
    }
}

/// No detection: every frame is `Scan` (a capture without interaction).
pub struct NoEvidence;

impl Evidence for NoEvidence {
    fn name(&self) -> &'static str {
        "none"
    }
    fn hysteresis(&self) -> Hysteresis {
        Hysteresis { on: f32::INFINITY, off: 0.0, min_on: 1, min_off: 1 }
    }
    fn evidence(&mut self, _f: &FrameView<'_>) -> f32 {
        0.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn run(evidence: &[f32], h: Hysteresis) -> (Vec<Phase>, Vec<MotionEvent>) {
        let mut t = WindowTracker::new(h);
        let mut phases = vec![None; evidence.len()];
        for (i, &e) in evidence.iter().enumerate() {
            for (k, p) in t.push(i, i, i as f64, e).0 {
                phases[k] = Some(p);
            }
        }
        for (k, p) in t.flush() {
            phases[k] = Some(p);
        }
        (phases.into_iter().map(|p| p.unwrap()).collect(), t.events)
    }

    #[test]
    fn hysteresis_ignores_blips_and_backdates_events() {
        let h = Hysteresis { on: 0.5, off: 0.5, min_on: 3, min_off: 3 };
        let e = [0., 1., 0., 0., 1., 1., 1., 1., 0., 1., 1., 0., 0., 0., 0., 1., 0.];
        let (p, ev) = run(&e, h);
        use Phase::*;
        assert_eq!(
            p,
            vec![
                Scan, Scan, Scan, Scan, Motion, Motion, Motion, Motion, Motion, Motion, Motion, After, After, After,
                After, After, After
            ]
        );
        assert_eq!(
            ev,
            vec![
                MotionEvent::HandIn { frame: 4, timestamp_s: 4.0 },
                MotionEvent::HandOut { frame: 11, timestamp_s: 11.0 }
            ]
        );
    }

    #[test]
    fn a_second_interaction_opens_a_second_window() {
        let h = Hysteresis { on: 0.5, off: 0.5, min_on: 2, min_off: 2 };
        let e = [0., 1., 1., 1., 0., 0., 0., 1., 0., 1., 1., 0., 0.];
        let (p, ev) = run(&e, h);
        use Phase::*;
        assert_eq!(
            p,
            vec![Scan, Motion, Motion, Motion, After, After, After, After, After, Motion, Motion, After, After]
        );
        let (hand_in, hand_out) = (
            |f: usize| MotionEvent::HandIn { frame: f, timestamp_s: f as f64 },
            |f: usize| MotionEvent::HandOut { frame: f, timestamp_s: f as f64 },
        );
        assert_eq!(ev, vec![hand_in(1), hand_out(4), hand_in(9), hand_out(11)]);
    }

    #[test]
    fn no_hand_no_window() {
        let (p, ev) = run(&[0.0; 20], Hysteresis::default());
        assert!(ev.is_empty());
        assert!(p.iter().all(|&x| x == Phase::Scan));
    }

    #[test]
    fn connected_skin_ignores_islands_inside_the_region() {
        let skin = image::Rgba([224, 172, 140, 255]);
        let grey = image::Rgba([120, 120, 120, 255]);
        let mut img = image::RgbaImage::from_pixel(100, 100, grey);
        // An island of skin inside the region (e.g. wood, food): ignored.
        for y in 40..50 {
            for x in 40..50 {
                img.put_pixel(x, y, skin);
            }
        }
        let rect = (25, 25, 75, 75);
        assert_eq!(connected_skin_fraction(&img, rect, 1), 0.0);
        // An arm from the bottom edge reaching into the region: counted.
        for y in 50..100 {
            for x in 45..52 {
                img.put_pixel(x, y, skin);
            }
        }
        let f = connected_skin_fraction(&img, rect, 1);
        let want = (7.0 * 25.0 + 100.0) / 2500.0; // arm inside the rect + the island it touches
        assert!((f - want).abs() < 1e-6, "{f} vs {want}");
    }

    #[test]
    fn skin_test_accepts_skin_and_rejects_grey_and_blue() {
        assert!(is_skin(224, 172, 140));
        assert!(is_skin(198, 134, 66) || is_skin(190, 140, 110));
        assert!(!is_skin(128, 128, 128));
        assert!(!is_skin(40, 60, 200));
        assert!(!is_skin(20, 10, 8));
    }
}
