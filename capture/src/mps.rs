//! Project Aria MPS outputs: `closed_loop_trajectory.csv` (T_world_device, quaternion
//! stored x,y,z,w, timestamps in microseconds on the device clock) and hand tracking
//! (`wrist_and_palm_poses.csv` v1/v2, `hand_tracking_results*.csv`; a confidence of -1
//! means the hand is missing) and the semidense point cloud (`semidense_points.csv.gz`:
//! world points with their distance uncertainty). Columns are found by header name,
//! so the v1 and v2 layouts and added columns all parse.

use std::collections::HashMap;
use std::path::Path;

use glam::{DQuat, DVec3};

use crate::calib::Se3;
use crate::error::{Error, Result};

/// A parsed CSV: header names and numeric rows (non-numeric cells are NaN, e.g. graph_uid).
struct Csv {
    cols: HashMap<String, usize>,
    rows: Vec<Vec<f64>>,
}

fn parse_csv(path: &Path, text: &str) -> Result<Csv> {
    let mut lines = text.lines().enumerate().filter(|(_, l)| !l.trim().is_empty());
    let (_, header) = lines.next().ok_or_else(|| Error::bad_file(path, "empty CSV"))?;
    let names: Vec<&str> = header.split(',').map(|s| s.trim()).collect();
    let cols: HashMap<String, usize> = names.iter().enumerate().map(|(i, n)| (n.to_string(), i)).collect();
    let mut rows = Vec::new();
    for (ln, line) in lines {
        let cells: Vec<f64> = line.split(',').map(|c| c.trim().parse::<f64>().unwrap_or(f64::NAN)).collect();
        if cells.len() != names.len() {
            return Err(Error::bad_file(
                path,
                format!("line {}: {} columns, header has {}", ln + 1, cells.len(), names.len()),
            ));
        }
        rows.push(cells);
    }
    Ok(Csv { cols, rows })
}

impl Csv {
    fn col(&self, path: &Path, name: &str) -> Result<usize> {
        self.cols.get(name).copied().ok_or_else(|| Error::bad_file(path, format!("CSV has no column {name:?}")))
    }
}

/// MPS semidense points: the SLAM's 3-D points in the world frame.
#[derive(Clone, Debug, Default)]
pub struct SemidensePoints {
    pub points: Vec<DVec3>,
    /// Standard deviation of each point's distance (metres).
    pub dist_std: Vec<f64>,
}

impl SemidensePoints {
    /// Parse semidense_points.csv (columns px_world, py_world, pz_world, dist_std).
    pub fn parse(path: &Path, text: &str) -> Result<Self> {
        let csv = parse_csv(path, text)?;
        let c: Vec<usize> =
            ["px_world", "py_world", "pz_world", "dist_std"].iter().map(|n| csv.col(path, n)).collect::<Result<_>>()?;
        let mut out = SemidensePoints::default();
        for (i, r) in csv.rows.iter().enumerate() {
            let v: Vec<f64> = c.iter().map(|&k| r[k]).collect();
            if v.iter().any(|x| !x.is_finite()) || v[3] < 0.0 {
                return Err(Error::bad_file(path, format!("row {}: invalid point", i + 2)));
            }
            out.points.push(DVec3::new(v[0], v[1], v[2]));
            out.dist_std.push(v[3]);
        }
        Ok(out)
    }

    /// Read semidense_points.csv or its gzip form (.gz), as MPS writes it.
    pub fn load(path: &Path) -> Result<Self> {
        let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
        let text = if path.extension().is_some_and(|e| e == "gz") {
            let mut text = String::new();
            std::io::Read::read_to_string(&mut flate2::read::GzDecoder::new(&bytes[..]), &mut text)
                .map_err(|e| Error::bad_file(path, format!("gzip: {e}")))?;
            text
        } else {
            String::from_utf8(bytes).map_err(|e| Error::bad_file(path, format!("not text: {e}")))?
        };
        Self::parse(path, &text)
    }

    /// The points whose distance is known to within `max_dist_std` metres.
    pub fn confident(&self, max_dist_std: f64) -> impl Iterator<Item = DVec3> + '_ {
        self.points.iter().zip(&self.dist_std).filter(move |(_, &s)| s <= max_dist_std).map(|(p, _)| *p)
    }
}

/// One pose sample of the device trajectory.
#[derive(Clone, Copy, Debug)]
pub struct PoseSample {
    pub t_us: i64,
    pub t_world_device: Se3,
}

/// A device trajectory sorted by time, interpolated at arbitrary timestamps.
#[derive(Clone, Debug, Default)]
pub struct Trajectory {
    pub samples: Vec<PoseSample>,
}

impl Trajectory {
    /// Parse closed_loop_trajectory.csv (or open_loop, or any CSV with the same columns).
    pub fn parse(path: &Path, text: &str) -> Result<Self> {
        let csv = parse_csv(path, text)?;
        let t = csv.col(path, "tracking_timestamp_us")?;
        let c: Vec<usize> = [
            "tx_world_device",
            "ty_world_device",
            "tz_world_device",
            "qx_world_device",
            "qy_world_device",
            "qz_world_device",
            "qw_world_device",
        ]
        .iter()
        .map(|n| csv.col(path, n))
        .collect::<Result<_>>()?;
        let mut samples = Vec::with_capacity(csv.rows.len());
        for (i, r) in csv.rows.iter().enumerate() {
            let v: Vec<f64> = c.iter().map(|&k| r[k]).collect();
            let q = DQuat::from_xyzw(v[3], v[4], v[5], v[6]);
            if !r[t].is_finite() || v.iter().any(|x| !x.is_finite()) || q.length() < 0.5 {
                return Err(Error::bad_file(path, format!("row {}: invalid pose", i + 2)));
            }
            samples.push(PoseSample { t_us: r[t] as i64, t_world_device: Se3::new(q, DVec3::new(v[0], v[1], v[2])) });
        }
        samples.sort_by_key(|s| s.t_us);
        Ok(Trajectory { samples })
    }

    pub fn load(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        Self::parse(path, &text)
    }

    /// T_world_device at `t_ns` (device clock), linear in translation and slerp in
    /// rotation between the two bracketing samples. None outside the trajectory's span
    /// (plus `tolerance_ns` of clamping at either end), and inside a hole in it (the
    /// nearer bracketing sample more than `tolerance_ns` away: tracking was lost
    /// there, and the head may have gone anywhere between the two).
    pub fn interpolate(&self, t_ns: i64, tolerance_ns: i64) -> Option<Se3> {
        let s = &self.samples;
        let first = s.first()?;
        let last = s.last()?;
        let t_us = t_ns as f64 / 1000.0;
        if t_us <= first.t_us as f64 {
            return ((first.t_us as f64 - t_us) * 1000.0 <= tolerance_ns as f64).then_some(first.t_world_device);
        }
        if t_us >= last.t_us as f64 {
            return ((t_us - last.t_us as f64) * 1000.0 <= tolerance_ns as f64).then_some(last.t_world_device);
        }
        let j = s.partition_point(|p| (p.t_us as f64) <= t_us);
        let (a, b) = (&s[j - 1], &s[j]);
        let nearer_us = (t_us - a.t_us as f64).min(b.t_us as f64 - t_us);
        if nearer_us * 1000.0 > tolerance_ns as f64 {
            return None;
        }
        let span = b.t_us as f64 - a.t_us as f64;
        let u = if span > 0.0 { (t_us - a.t_us as f64) / span } else { 0.0 };
        Some(a.t_world_device.interpolate(&b.t_world_device, u))
    }

    /// Time span in microseconds.
    pub fn span_us(&self) -> Option<(i64, i64)> {
        Some((self.samples.first()?.t_us, self.samples.last()?.t_us))
    }
}

/// One hand's observation in device coordinates.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HandObservation {
    pub confidence: f64,
    pub wrist_device: DVec3,
    pub palm_device: DVec3,
}

/// Both hands at one timestamp; None when the hand is missing (confidence -1).
#[derive(Clone, Copy, Debug)]
pub struct HandSample {
    pub t_us: i64,
    pub left: Option<HandObservation>,
    pub right: Option<HandObservation>,
}

impl HandSample {
    pub fn hands(&self) -> impl Iterator<Item = &HandObservation> {
        self.left.iter().chain(self.right.iter())
    }
}

/// Hand tracking results sorted by time.
#[derive(Clone, Debug, Default)]
pub struct HandTracking {
    pub samples: Vec<HandSample>,
}

impl HandTracking {
    /// Parse wrist_and_palm_poses.csv (v1 or v2) or hand_tracking_results*.csv.
    pub fn parse(path: &Path, text: &str) -> Result<Self> {
        let csv = parse_csv(path, text)?;
        let t = csv.col(path, "tracking_timestamp_us")?;
        let side = |s: &str| -> Result<SideCols> {
            let conf = csv.col(path, &format!("{s}_tracking_confidence"))?;
            let get3 = |fmt: &dyn Fn(&str) -> String| -> Option<[usize; 3]> {
                Some([csv.cols.get(&fmt("x"))?.to_owned(), *csv.cols.get(&fmt("y"))?, *csv.cols.get(&fmt("z"))?])
            };
            // wrist_and_palm_poses: t{x,y,z}_{s}_wrist_device / _palm_device.
            // hand_tracking_results: t{x,y,z}_{s}_device_wrist and 21 landmarks.
            let wrist =
                get3(&|a| format!("t{a}_{s}_wrist_device")).or_else(|| get3(&|a| format!("t{a}_{s}_device_wrist")));
            let palm = get3(&|a| format!("t{a}_{s}_palm_device"));
            let landmarks: Vec<[usize; 3]> =
                (0..21).filter_map(|k| get3(&|a| format!("t{a}_{s}_landmark_{k}_device"))).collect();
            let wrist = wrist.ok_or_else(|| Error::bad_file(path, format!("CSV has no {s} wrist columns")))?;
            Ok(SideCols { conf, wrist, palm, landmarks })
        };
        let (lc, rc) = (side("left")?, side("right")?);
        let mut samples = Vec::with_capacity(csv.rows.len());
        for (i, r) in csv.rows.iter().enumerate() {
            if !r[t].is_finite() {
                return Err(Error::bad_file(path, format!("row {}: bad timestamp", i + 2)));
            }
            samples.push(HandSample { t_us: r[t] as i64, left: lc.read(r), right: rc.read(r) });
        }
        samples.sort_by_key(|s| s.t_us);
        Ok(HandTracking { samples })
    }

    pub fn load(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        Self::parse(path, &text)
    }

    /// The sample nearest to `t_ns` if it lies within `max_gap_ns`.
    pub fn nearest(&self, t_ns: i64, max_gap_ns: i64) -> Option<&HandSample> {
        let t_us = t_ns.div_euclid(1000);
        let j = self.samples.partition_point(|s| s.t_us < t_us);
        let cands = [j.checked_sub(1), Some(j)];
        cands
            .iter()
            .flatten()
            .filter_map(|&k| self.samples.get(k))
            .min_by_key(|s| s.t_us.abs_diff(t_us))
            .filter(|s| s.t_us.abs_diff(t_us).saturating_mul(1000) <= max_gap_ns.max(0) as u64)
    }
}

impl HandTracking {
    /// World positions of the palms seen at `t_ns` (device clock) with at least
    /// `min_confidence`: each hand's palm interpolated between the two hand samples
    /// around `t_ns` (the nearer one alone when only it saw that hand), within
    /// `max_gap_ns`, placed in the world by the device pose at its own time.
    pub fn palms_in_world(
        &self,
        trajectory: &Trajectory,
        t_ns: i64,
        max_gap_ns: i64,
        min_confidence: f64,
    ) -> Vec<DVec3> {
        let t_us = t_ns as f64 / 1000.0;
        let j = self.samples.partition_point(|s| (s.t_us as f64) < t_us);
        let near = |k: Option<usize>| {
            k.and_then(|k| self.samples.get(k)).filter(|s| (s.t_us as f64 - t_us).abs() * 1000.0 <= max_gap_ns as f64)
        };
        let (before, after) = (near(j.checked_sub(1)), near(Some(j)));
        let world = |s: &HandSample, h: &HandObservation| {
            trajectory.interpolate(s.t_us * 1000, max_gap_ns).map(|p| p.transform_point(h.palm_device))
        };
        let confident = |s: Option<&HandSample>, side: fn(&HandSample) -> Option<HandObservation>| {
            s.and_then(|s| {
                side(s).filter(|h| h.confidence >= min_confidence).and_then(|h| world(s, &h)).map(|p| (s.t_us, p))
            })
        };
        let sides: [fn(&HandSample) -> Option<HandObservation>; 2] = [|s| s.left, |s| s.right];
        sides
            .iter()
            .filter_map(|&side| match (confident(before, side), confident(after, side)) {
                (Some((ta, a)), Some((tb, b))) if tb > ta => Some(a.lerp(b, (t_us - ta as f64) / (tb - ta) as f64)),
                (Some((ta, a)), Some((tb, b))) => {
                    Some(if (t_us - ta as f64).abs() <= (tb as f64 - t_us).abs() { a } else { b })
                }
                (a, b) => a.or(b).map(|(_, p)| p),
            })
            .collect()
    }
}

struct SideCols {
    conf: usize,
    wrist: [usize; 3],
    palm: Option<[usize; 3]>,
    landmarks: Vec<[usize; 3]>,
}

impl SideCols {
    fn read(&self, r: &[f64]) -> Option<HandObservation> {
        let c = r[self.conf];
        if !c.is_finite() || c < 0.0 {
            return None;
        }
        let v = |k: [usize; 3]| DVec3::new(r[k[0]], r[k[1]], r[k[2]]);
        let wrist = v(self.wrist);
        let palm = match self.palm {
            Some(p) => v(p),
            None if !self.landmarks.is_empty() => {
                self.landmarks.iter().map(|&k| v(k)).sum::<DVec3>() / self.landmarks.len() as f64
            }
            None => wrist,
        };
        (wrist.is_finite() && palm.is_finite()).then_some(HandObservation {
            confidence: c,
            wrist_device: wrist,
            palm_device: palm,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const TRAJECTORY_HEADER: &str = "tracking_timestamp_us,tx_world_device,ty_world_device,tz_world_device,qx_world_device,qy_world_device,qz_world_device,qw_world_device\n";

    #[test]
    fn trajectory_interpolates_linearly_and_by_slerp() {
        let text =
            format!("{TRAJECTORY_HEADER}1000,0,0,0,0,0,0,1\n2000,2,0,0,0,0,0.7071067811865476,0.7071067811865476\n");
        let t = Trajectory::parse(Path::new("t.csv"), &text).unwrap();
        let p = t.interpolate(1_500_000, 500_000).unwrap();
        assert!((p.translation - DVec3::new(1.0, 0.0, 0.0)).length() < 1e-12);
        let angle = p.rotation.angle_between(DQuat::IDENTITY);
        assert!((angle - std::f64::consts::FRAC_PI_4).abs() < 1e-9, "{angle}");
        assert!(t.interpolate(3_000_000, 0).is_none());
        assert!(t.interpolate(2_000_500, 1000).is_some());
        // A hole: 1 ms between the samples is tracking lost for a 0.4 ms tolerance,
        // except within the tolerance of either sample.
        assert!(t.interpolate(1_500_000, 400_000).is_none(), "the middle of a hole");
        assert!(t.interpolate(1_300_000, 400_000).is_some(), "near a sample");
    }

    #[test]
    fn palms_are_placed_in_the_world_between_hand_samples() {
        let trajectory = format!("{TRAJECTORY_HEADER}1000,0,0,0,0,0,0,1\n2000,2,0,0,0,0,0,1\n");
        let trajectory = Trajectory::parse(Path::new("t.csv"), &trajectory).unwrap();
        let hands = "tracking_timestamp_us,left_tracking_confidence,tx_left_wrist_device,ty_left_wrist_device,tz_left_wrist_device,tx_left_palm_device,ty_left_palm_device,tz_left_palm_device,right_tracking_confidence,tx_right_wrist_device,ty_right_wrist_device,tz_right_wrist_device,tx_right_palm_device,ty_right_palm_device,tz_right_palm_device\n\
                     1000,0.2,0,0,0,5,5,5,0.9,0,0,0,0,0,1\n\
                     2000,0.2,0,0,0,5,5,5,0.9,0,0,0,0,0,3\n";
        let hands = HandTracking::parse(Path::new("h.csv"), hands).unwrap();
        // Device at x = 0 then 2, palm 1 then 3 m ahead of it: halfway, (1, 0, 2).
        let palms = hands.palms_in_world(&trajectory, 1_500_000, 1_000_000, 0.5);
        assert_eq!(palms.len(), 1, "the unconfident left hand is left out: {palms:?}");
        assert!((palms[0] - DVec3::new(1.0, 0.0, 2.0)).length() < 1e-9, "{palms:?}");
        let near_the_end = hands.palms_in_world(&trajectory, 2_050_000, 100_000, 0.5);
        assert!((near_the_end[0] - DVec3::new(2.0, 0.0, 3.0)).length() < 1e-9, "{near_the_end:?}");
        assert!(hands.palms_in_world(&trajectory, 2_500_000, 100_000, 0.5).is_empty(), "no sample within the gap");
        assert_eq!(hands.palms_in_world(&trajectory, 1_500_000, 1_000_000, 0.1).len(), 2);
    }

    #[test]
    fn semidense_points_read_plain_and_gzipped_and_filter_by_uncertainty() {
        let text = "uid,graph_uid,px_world,py_world,pz_world,inv_dist_std,dist_std\n\
                    0,g,1.5,-2,0.25,0.001,0.004\n\
                    1,g,0,0,3,0.01,0.2\n";
        let dir = std::env::temp_dir().join(format!("aim-semidense-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let plain = dir.join("semidense_points.csv");
        std::fs::write(&plain, text).unwrap();
        let gz = dir.join("semidense_points.csv.gz");
        let mut enc = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
        std::io::Write::write_all(&mut enc, text.as_bytes()).unwrap();
        std::fs::write(&gz, enc.finish().unwrap()).unwrap();
        for path in [&plain, &gz] {
            let pts = SemidensePoints::load(path).unwrap();
            assert_eq!(pts.points, vec![DVec3::new(1.5, -2.0, 0.25), DVec3::new(0.0, 0.0, 3.0)]);
            assert_eq!(pts.dist_std, vec![0.004, 0.2]);
            assert_eq!(pts.confident(0.05).collect::<Vec<_>>(), vec![DVec3::new(1.5, -2.0, 0.25)]);
        }
        // A row with a missing coordinate, or a file that is not gzip, names the file.
        std::fs::write(&plain, "uid,px_world,py_world,pz_world,dist_std\n0,1,,2,0.1\n").unwrap();
        let e = SemidensePoints::load(&plain).unwrap_err().to_string();
        assert!(e.contains("semidense_points.csv") && e.contains("row 2"), "{e}");
        std::fs::write(&gz, text).unwrap();
        let e = SemidensePoints::load(&gz).unwrap_err().to_string();
        assert!(e.contains("semidense_points.csv.gz") && e.contains("gzip"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn missing_column_names_the_file() {
        let e = Trajectory::parse(Path::new("traj.csv"), "a,b\n1,2\n").unwrap_err();
        assert!(e.to_string().contains("traj.csv") && e.to_string().contains("tracking_timestamp_us"));
    }

    #[test]
    fn ragged_row_is_an_error() {
        let e = HandTracking::parse(Path::new("h.csv"), "tracking_timestamp_us,left_tracking_confidence\n1,2,3\n");
        assert!(e.is_err());
    }
}
