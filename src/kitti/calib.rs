//! `calib.txt`: the rectified projection matrices `P0`..`P3` (3x4, row-major) and `Tr`
//! (velodyne → rectified cam0, 3x4). Odometry files have rectification folded in (R0_rect = I);
//! object-detection style files name it `Tr_velo_to_cam` and add `R0_rect`, both accepted.

use std::path::Path;

use anyhow::{bail, Context, Result};
use nalgebra::{Matrix3, Vector3};

use super::{format_kitti_number, poses::parse_floats};
use crate::atomic_file::write_atomic;
use crate::geometry::{Intrinsics, Pose, check_rotation};

/// The camera whose images the project uses: KITTI's left colour camera, `image_2`.
pub const COLOR_CAMERA: usize = 2;

#[derive(Debug, Clone, PartialEq)]
pub struct Calib {
    /// `P0`..`P3`, row-major 3x4, absent when the file lacks that line.
    pub projections: [Option<[f64; 12]>; 4],
    /// velodyne → (unrectified when `r0_rect` is set, else rectified) cam0.
    pub velo_to_cam0: Pose,
    /// Rectifying rotation when the file gives one (not in odometry files).
    pub r0_rect: Option<Matrix3<f64>>,
}

impl Calib {
    pub fn parse(text: &str, origin: &str) -> Result<Self> {
        let mut projections = [None; 4];
        let mut velo_to_cam0 = None;
        let mut r0_rect = None;
        for (line_no, line) in text.lines().enumerate() {
            let at = || format!("{origin}:{}", line_no + 1);
            if line.trim().is_empty() {
                continue;
            }
            let Some((key, values)) = line.split_once(':') else {
                bail!("{}: expected `KEY: numbers`, found `{}`", at(), line.trim());
            };
            match key.trim() {
                k @ ("P0" | "P1" | "P2" | "P3") => {
                    let v = parse_floats(values, 12).with_context(|| format!("{} ({k})", at()))?;
                    let index = (k.as_bytes()[1] - b'0') as usize;
                    projections[index] = Some(v.try_into().unwrap());
                }
                k @ ("Tr" | "Tr_velo_to_cam") => {
                    let v = parse_floats(values, 12).with_context(|| format!("{} ({k})", at()))?;
                    let pose = Pose::from_row_major_3x4(&v.try_into().unwrap())
                        .map_err(|e| anyhow::anyhow!("{}: {k}'s rotation block {e}", at()))?;
                    velo_to_cam0 = Some(pose);
                }
                k @ ("R0_rect" | "R_rect") => {
                    let v = parse_floats(values, 9).with_context(|| format!("{} ({k})", at()))?;
                    let r = Matrix3::from_row_slice(&v);
                    check_rotation(&r).map_err(|e| anyhow::anyhow!("{}: {k} {e}", at()))?;
                    r0_rect = Some(r);
                }
                // Other keys (Tr_imu_to_velo, ...) are not needed here.
                _ => {}
            }
        }
        let Some(velo_to_cam0) = velo_to_cam0 else {
            bail!("{origin}: no `Tr:` (velodyne to camera) line");
        };
        if projections[COLOR_CAMERA].is_none() {
            bail!("{origin}: no `P2:` line (the colour camera's projection)");
        }
        Ok(Calib { projections, velo_to_cam0, r0_rect })
    }

    pub fn read(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
        Self::parse(&text, &path.display().to_string())
    }

    /// The odometry-style text: `P0`..`P3` (missing ones omitted) then `Tr`.
    pub fn to_text(&self) -> String {
        let row = |values: &[f64]| values.iter().map(|v| format_kitti_number(*v)).collect::<Vec<_>>().join(" ");
        let mut text = String::new();
        for (i, p) in self.projections.iter().enumerate() {
            if let Some(p) = p {
                text.push_str(&format!("P{i}: {}\n", row(p)));
            }
        }
        if let Some(r) = &self.r0_rect {
            let values: Vec<f64> = (0..9).map(|k| r[(k / 3, k % 3)]).collect();
            text.push_str(&format!("R0_rect: {}\n", row(&values)));
        }
        text.push_str(&format!("Tr: {}\n", row(&self.velo_to_cam0.to_row_major_3x4())));
        text
    }

    pub fn write(&self, path: &Path) -> Result<()> {
        Ok(write_atomic(path, self.to_text().as_bytes())?)
    }

    fn projection(&self, camera: usize) -> Result<&[f64; 12]> {
        self.projections
            .get(camera)
            .and_then(|p| p.as_ref())
            .with_context(|| format!("calibration has no P{camera}"))
    }

    /// Pinhole intrinsics of rectified camera `camera`: fx = P[0,0], fy = P[1,1], cx = P[0,2], cy = P[1,2].
    pub fn intrinsics(&self, camera: usize) -> Result<Intrinsics> {
        let p = self.projection(camera)?;
        let k = Intrinsics { fx: p[0], fy: p[5], cx: p[2], cy: p[6] };
        k.validate().map_err(anyhow::Error::msg)?;
        Ok(k)
    }

    /// camera_from_lidar for rectified camera `camera`: `[I | t] · R0_rect · Tr` with
    /// t = (P[0,3]/P[0,0], P[1,3]/P[1,1], P[2,3]), the offset of that camera from cam0.
    pub fn camera_from_lidar(&self, camera: usize) -> Result<Pose> {
        let p = self.projection(camera)?;
        let offset = Pose::from_rt(Matrix3::identity(), Vector3::new(p[3] / p[0], p[7] / p[5], p[11]));
        let rect = match &self.r0_rect {
            Some(r) => Pose::from_rt(*r, Vector3::zeros()),
            None => Pose::identity(),
        };
        Ok(offset.compose(&rect).compose(&self.velo_to_cam0))
    }

    /// Rectified cam0_from_lidar: `R0_rect · Tr` (the frame KITTI's `poses.txt` is given in).
    pub fn rectified_cam0_from_lidar(&self) -> Pose {
        match &self.r0_rect {
            Some(r) => Pose::from_rt(*r, Vector3::zeros()).compose(&self.velo_to_cam0),
            None => self.velo_to_cam0,
        }
    }

    /// The colour camera's (image_2) intrinsics.
    pub fn color_intrinsics(&self) -> Result<Intrinsics> {
        self.intrinsics(COLOR_CAMERA)
    }

    /// The colour camera's (image_2) camera_from_lidar.
    pub fn color_camera_from_lidar(&self) -> Result<Pose> {
        self.camera_from_lidar(COLOR_CAMERA)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Point3;

    /// Sequence 00's calib.txt from KITTI odometry, verbatim.
    const KITTI_00: &str = "P0: 7.188560000000e+02 0.000000000000e+00 6.071928000000e+02 0.000000000000e+00 0.000000000000e+00 7.188560000000e+02 1.852157000000e+02 0.000000000000e+00 0.000000000000e+00 0.000000000000e+00 1.000000000000e+00 0.000000000000e+00
P1: 7.188560000000e+02 0.000000000000e+00 6.071928000000e+02 -3.861448000000e+02 0.000000000000e+00 7.188560000000e+02 1.852157000000e+02 0.000000000000e+00 0.000000000000e+00 0.000000000000e+00 1.000000000000e+00 0.000000000000e+00
P2: 7.188560000000e+02 0.000000000000e+00 6.071928000000e+02 4.538225000000e+01 0.000000000000e+00 7.188560000000e+02 1.852157000000e+02 -1.130887000000e-01 0.000000000000e+00 0.000000000000e+00 1.000000000000e+00 3.779761000000e-03
P3: 7.188560000000e+02 0.000000000000e+00 6.071928000000e+02 -3.372877000000e+02 0.000000000000e+00 7.188560000000e+02 1.852157000000e+02 2.369057000000e+00 0.000000000000e+00 0.000000000000e+00 1.000000000000e+00 4.915215000000e-03
Tr: 4.276802385584e-04 -9.999672484946e-01 -8.084491683471e-03 -1.198459927713e-02 -7.210626507497e-03 8.081198471645e-03 -9.999413164504e-01 -5.403984729748e-02 9.999738645903e-01 4.859485810390e-04 -7.206933692422e-03 -2.921968648686e-01
";

    #[test]
    fn parses_real_kitti_and_builds_image_2_extrinsics() {
        let calib = Calib::parse(KITTI_00, "00/calib.txt").unwrap();
        let k = calib.color_intrinsics().unwrap();
        assert_eq!((k.fx, k.fy, k.cx, k.cy), (718.856, 718.856, 607.1928, 185.2157));
        let cam2 = calib.color_camera_from_lidar().unwrap();
        let cam0 = calib.velo_to_cam0;
        // image_2 sits ~6 cm to the left of cam0: the same point has x larger by P2[0,3]/fx.
        let p = Point3::new(10.0, 1.0, -0.5);
        let d = cam2.transform(&p) - cam0.transform(&p);
        assert!((d.x - 45.38225 / 718.856).abs() < 1e-12);
        assert!((d.y + 0.1130887 / 718.856).abs() < 1e-12);
        assert!((d.z - 3.779761e-3).abs() < 1e-12);
    }

    #[test]
    fn text_round_trip_is_exact() {
        let calib = Calib::parse(KITTI_00, "00/calib.txt").unwrap();
        let back = Calib::parse(&calib.to_text(), "again").unwrap();
        assert_eq!(back.projections, calib.projections);
        assert!((back.velo_to_cam0.matrix() - calib.velo_to_cam0.matrix()).abs().max() < 1e-12);
    }

    #[test]
    fn errors_name_file_and_line() {
        let err = format!("{:#}", Calib::parse("P2: 1 2 3\nTr: 1 0 0 0 0 1 0 0 0 0 1 0\n", "c.txt").unwrap_err());
        assert!(err.contains("c.txt:1") && err.contains("P2"), "{err}");
        let err = Calib::parse("P2: 1 0 0 0 0 1 0 0 0 0 1 0\n", "c.txt").unwrap_err().to_string();
        assert!(err.contains("no `Tr:`"), "{err}");
        let err = format!("{:#}", Calib::parse("Tr: 2 0 0 0 0 1 0 0 0 0 1 0\n", "c.txt").unwrap_err());
        assert!(err.contains("c.txt:1") && err.contains("not a rotation"), "{err}");
        // A reflection passes orthonormality but not the determinant; R0_rect is checked too.
        let err = format!("{:#}", Calib::parse("P2: 1 0 0 0 0 1 0 0 0 0 1 0\nTr: 1 0 0 0 0 1 0 0 0 0 -1 0\n", "c.txt").unwrap_err());
        assert!(err.starts_with("c.txt:2: Tr's rotation block is not a rotation") && err.contains("reflection"), "{err}");
        let err = format!("{:#}", Calib::parse("R0_rect: 0 0 0 0 0 0 0 0 0\n", "c.txt").unwrap_err());
        assert!(err.starts_with("c.txt:1: R0_rect is not a rotation: every entry is 0"), "{err}");
        let bad = "P2: 1 0 0 0 0 1 0 0 0 0 1 x\nTr: 1 0 0 0 0 1 0 0 0 0 1 0\n";
        let err = format!("{:#}", Calib::parse(bad, "c.txt").unwrap_err());
        assert!(err.contains("`x` is not a number"), "{err}");
    }
}
