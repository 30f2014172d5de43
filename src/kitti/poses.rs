//! `poses.txt`: one line per frame, 12 row-major floats = world_from_cam0 of that frame, where
//! "world" is cam0's frame at frame 0 (KITTI-odometry's ground-truth convention).

use std::path::Path;

use anyhow::{bail, Context, Result};

use super::format_kitti_number;
use crate::atomic_file::write_atomic;
use crate::geometry::Pose;

/// Parses poses text; `origin` names the file in errors, which also give the line number.
/// Errors: a line without exactly 12 finite numbers, or whose 3x3 block (numbers 1-3, 5-7,
/// 9-11) is not a rotation within `geometry::ROTATION_TOLERANCE` (`geometry::check_rotation`:
/// an all-zero block from a lost track, a scaled or reflected one); nothing is repaired.
pub fn parse_poses(text: &str, origin: &str) -> Result<Vec<Pose>> {
    let mut poses = Vec::new();
    for (line_no, line) in text.lines().enumerate() {
        if line.trim().is_empty() {
            continue;
        }
        let at = || format!("{origin}:{}", line_no + 1);
        let values = parse_floats(line, 12).with_context(at)?;
        let pose = Pose::from_row_major_3x4(&values.try_into().unwrap())
            .map_err(|e| anyhow::anyhow!("{}: the pose's rotation block (numbers 1-3, 5-7, 9-11) {e}", at()))?;
        poses.push(pose);
    }
    Ok(poses)
}

pub fn read_poses(path: &Path) -> Result<Vec<Pose>> {
    let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    parse_poses(&text, &path.display().to_string())
}

pub fn poses_to_text(poses: &[Pose]) -> String {
    let mut text = String::new();
    for pose in poses {
        let numbers: Vec<String> = pose.to_row_major_3x4().iter().map(|v| format_kitti_number(*v)).collect();
        text.push_str(&numbers.join(" "));
        text.push('\n');
    }
    text
}

pub fn write_poses(path: &Path, poses: &[Pose]) -> Result<()> {
    Ok(write_atomic(path, poses_to_text(poses).as_bytes())?)
}

/// Parses exactly `count` whitespace-separated floats.
pub(crate) fn parse_floats(text: &str, count: usize) -> Result<Vec<f64>> {
    let mut values = Vec::with_capacity(count);
    for token in text.split_whitespace() {
        let v: f64 = token.parse().with_context(|| format!("`{token}` is not a number"))?;
        if !v.is_finite() {
            bail!("`{token}` is not a finite number");
        }
        values.push(v);
    }
    if values.len() != count {
        bail!("expected {count} numbers, found {}", values.len());
    }
    Ok(values)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_errors_name_the_line() {
        let poses = vec![Pose::identity(), Pose::ground_motion(0.3, 1.25, -4.0)];
        let back = parse_poses(&poses_to_text(&poses), "p").unwrap();
        assert_eq!(back.len(), 2);
        for (a, b) in poses.iter().zip(&back) {
            assert!((a.matrix() - b.matrix()).abs().max() < 1e-11);
        }
        let err = format!("{:#}", parse_poses("1 0 0 0 0 1 0 0 0 0 1 0\n1 2 3\n", "poses.txt").unwrap_err());
        assert!(err.contains("poses.txt:2") && err.contains("expected 12"), "{err}");
        // A lost track (all-zero rotation) and R00 = 2 are refused, naming the line.
        let ok = "1 0 0 0 0 1 0 0 0 0 1 0\n";
        let err = format!("{:#}", parse_poses(&format!("{ok}\n{ok}0 0 0 5 0 0 0 6 0 0 0 7\n"), "poses.txt").unwrap_err());
        assert!(err.starts_with("poses.txt:4: the pose's rotation block") && err.contains("every entry is 0"), "{err}");
        let err = format!("{:#}", parse_poses(&format!("{ok}2 0 0 0 0 1 0 0 0 0 1 0\n"), "poses.txt").unwrap_err());
        assert!(err.starts_with("poses.txt:2:") && err.contains("lengths 2.0000, 1.0000, 1.0000"), "{err}");
    }
}
