//! Finding sequences on disk and the per-frame view the rest of the project uses.
//!
//! Accepted roots: a KITTI `dataset/` directory (`sequences/NN/`, poses in `poses/NN.txt`), a
//! directory whose sub-directories are sequences, or a single sequence directory.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};

use super::{calib::Calib, poses::read_poses, velodyne::{read_velodyne, LidarPoint}};
use crate::geometry::{Intrinsics, Pose};

/// One sequence: its calibration, optional ground-truth poses and the frames found on disk.
#[derive(Debug, Clone)]
pub struct Sequence {
    /// The directory name (e.g. `00`).
    pub name: String,
    pub dir: PathBuf,
    pub calib: Calib,
    /// world_from_cam0 per frame index, when a poses file exists.
    pub poses: Option<Vec<Pose>>,
    /// Frame indices with a `velodyne/NNNNNN.bin`, ascending.
    pub frame_indices: Vec<usize>,
}

/// One frame of a sequence: where its files are and the rig quantities the pipeline needs.
#[derive(Debug, Clone)]
pub struct Frame {
    pub sequence: String,
    pub index: usize,
    pub velodyne_path: PathBuf,
    pub image_path: PathBuf,
    /// image_2's camera_from_lidar (`[I | t2] · Tr`).
    pub camera_from_lidar: Pose,
    pub intrinsics: Intrinsics,
    /// world_from_cam0 from the poses file, when there is one.
    pub world_from_cam0: Option<Pose>,
}

impl Frame {
    pub fn read_points(&self) -> Result<Vec<LidarPoint>> {
        read_velodyne(&self.velodyne_path)
    }

    /// (width, height) of image_2, read from the PNG header only.
    pub fn image_size(&self) -> Result<(u32, u32)> {
        image::image_dimensions(&self.image_path).with_context(|| format!("reading {}", self.image_path.display()))
    }

    pub fn read_image(&self) -> Result<image::RgbImage> {
        Ok(image::open(&self.image_path)
            .with_context(|| format!("reading {}", self.image_path.display()))?
            .to_rgb8())
    }
}

impl Sequence {
    /// Opens one sequence directory; `poses_override` is real KITTI's `poses/NN.txt`.
    pub fn open(dir: &Path, poses_override: Option<&Path>) -> Result<Self> {
        let name = dir
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_else(|| dir.display().to_string());
        let calib = Calib::read(&dir.join("calib.txt"))?;
        let velodyne_dir = dir.join("velodyne");
        let mut frame_indices = Vec::new();
        for entry in std::fs::read_dir(&velodyne_dir).with_context(|| format!("listing {}", velodyne_dir.display()))? {
            let file_name = entry?.file_name();
            let file_name = file_name.to_string_lossy();
            if let Some(stem) = file_name.strip_suffix(".bin") {
                if let Ok(index) = stem.parse::<usize>() {
                    frame_indices.push(index);
                }
            }
        }
        frame_indices.sort_unstable();
        let poses_path = match poses_override {
            Some(p) if p.exists() => Some(p.to_path_buf()),
            _ => Some(dir.join("poses.txt")).filter(|p| p.exists()),
        };
        let poses = poses_path.as_deref().map(read_poses).transpose()?;
        if let (Some(poses), Some(&last)) = (&poses, frame_indices.last()) {
            if last >= poses.len() {
                bail!(
                    "{}: has {} poses but velodyne/ goes up to frame {last}",
                    poses_path.unwrap().display(),
                    poses.len()
                );
            }
        }
        Ok(Sequence { name, dir: dir.to_path_buf(), calib, poses, frame_indices })
    }

    pub fn len(&self) -> usize {
        self.frame_indices.len()
    }

    pub fn is_empty(&self) -> bool {
        self.frame_indices.is_empty()
    }

    /// The frame with file index `index` (the NNNNNN in the file names).
    pub fn frame(&self, index: usize) -> Result<Frame> {
        if self.frame_indices.binary_search(&index).is_err() {
            bail!("sequence {} ({}) has no frame {index}", self.name, self.dir.display());
        }
        Ok(Frame {
            sequence: self.name.clone(),
            index,
            velodyne_path: self.dir.join("velodyne").join(format!("{index:06}.bin")),
            image_path: self.dir.join("image_2").join(format!("{index:06}.png")),
            camera_from_lidar: self.calib.color_camera_from_lidar()?,
            intrinsics: self.calib.color_intrinsics()?,
            world_from_cam0: self.poses.as_ref().map(|p| p[index]),
        })
    }

    /// All frames in index order.
    pub fn frames(&self) -> Result<Vec<Frame>> {
        self.frame_indices.iter().map(|&i| self.frame(i)).collect()
    }

    // --- The sequence's map frame -------------------------------------------------------------
    //
    // `poses.txt` gives world_from_cam0 with world = cam0 at frame 0: a y-down camera frame. The
    // model and the map store work in a z-up map frame, so a sequence's map frame is the same
    // place expressed in the LiDAR's axes: **the velodyne frame at frame 0** (x forward, y left,
    // z up). map_from_lidar(k) = C⁻¹ · world_from_cam0(k) · C with C = rectified cam0_from_lidar
    // (`R0_rect · Tr`). A map fused from the sequence's scans, the truth of every frame and a
    // tracked trajectory all use this frame.

    fn pose_of(&self, index: usize) -> Result<Pose> {
        let poses = self.poses.as_ref().with_context(|| format!("sequence {} ({}) has no poses file", self.name, self.dir.display()))?;
        poses.get(index).copied().with_context(|| format!("sequence {} has no pose for frame {index}", self.name))
    }

    /// map_from_lidar of frame `index` (the scan's placement in the sequence's map frame, above).
    /// Errors: no poses file, or no pose for that frame.
    pub fn map_from_lidar(&self, index: usize) -> Result<Pose> {
        let c = self.calib.rectified_cam0_from_lidar();
        Ok(c.inverse().compose(&self.pose_of(index)?).compose(&c))
    }

    /// The true camera_from_map of image_2 at frame `index`: camera_from_lidar · map_from_lidar⁻¹.
    pub fn camera_from_map(&self, index: usize) -> Result<Pose> {
        Ok(self.calib.color_camera_from_lidar()?.compose(&self.map_from_lidar(index)?.inverse()))
    }

    /// The inverse of [`Sequence::camera_from_map`]: the `poses.txt` line (world_from_cam0,
    /// world = cam0 at frame 0) of an image_2 camera_from_map in the map frame, so estimated
    /// trajectories are written in the same convention as the ground truth.
    pub fn world_from_cam0(&self, camera_from_map: &Pose) -> Result<Pose> {
        let c = self.calib.rectified_cam0_from_lidar();
        let map_from_lidar = camera_from_map.inverse().compose(&self.calib.color_camera_from_lidar()?);
        Ok(c.compose(&map_from_lidar).compose(&c.inverse()))
    }

    /// Frame `index`'s scan in the sequence's map frame (intensity kept).
    pub fn scan_in_map_frame(&self, index: usize) -> Result<Vec<LidarPoint>> {
        let map_from_lidar = self.map_from_lidar(index)?;
        let points = self.frame(index)?.read_points()?;
        Ok(points
            .into_iter()
            .map(|p| {
                let m = map_from_lidar.transform(&nalgebra::Point3::new(p.x as f64, p.y as f64, p.z as f64));
                LidarPoint { x: m.x as f32, y: m.y as f32, z: m.z as f32, intensity: p.intensity }
            })
            .collect())
    }

    /// Seconds per frame from `times.txt` (one number a line, KITTI-odometry's timestamps),
    /// `None` when the sequence has no such file. Errors: unreadable file, a bad line, fewer
    /// lines than frames.
    pub fn times(&self) -> Result<Option<Vec<f64>>> {
        let path = self.dir.join("times.txt");
        let text = match std::fs::read_to_string(&path) {
            Ok(text) => text,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(e).with_context(|| format!("reading {}", path.display())),
        };
        let mut times = Vec::new();
        for (line_no, line) in text.lines().enumerate().filter(|(_, l)| !l.trim().is_empty()) {
            let v = super::poses::parse_floats(line, 1).with_context(|| format!("{}:{}", path.display(), line_no + 1))?;
            times.push(v[0]);
        }
        if let Some(&last) = self.frame_indices.last() {
            if last >= times.len() {
                bail!("{}: has {} times but velodyne/ goes up to frame {last}", path.display(), times.len());
            }
        }
        Ok(Some(times))
    }
}

fn is_sequence_dir(dir: &Path) -> bool {
    dir.join("calib.txt").is_file() && dir.join("velodyne").is_dir()
}

/// Every sequence under `root`, sorted by name (see the module doc for the accepted layouts).
pub fn discover_sequences(root: &Path) -> Result<Vec<Sequence>> {
    if !root.is_dir() {
        bail!("{} is not a directory", root.display());
    }
    if is_sequence_dir(root) {
        return Ok(vec![Sequence::open(root, None)?]);
    }
    let (parent, poses_dir) = if root.join("sequences").is_dir() {
        (root.join("sequences"), Some(root.join("poses")))
    } else {
        (root.to_path_buf(), None)
    };
    let mut dirs: Vec<PathBuf> = std::fs::read_dir(&parent)
        .with_context(|| format!("listing {}", parent.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| is_sequence_dir(p))
        .collect();
    dirs.sort();
    if dirs.is_empty() {
        bail!(
            "{}: no KITTI sequence found (expected calib.txt and velodyne/ in the directory, in its sub-directories, or under sequences/)",
            root.display()
        );
    }
    dirs.iter()
        .map(|dir| {
            let poses = poses_dir.as_ref().map(|p| p.join(format!("{}.txt", dir.file_name().unwrap().to_string_lossy())));
            Sequence::open(dir, poses.as_deref())
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::atomic_file::write_atomic;
    use crate::kitti::{velodyne::write_velodyne, write_poses};

    fn write_sequence(dir: &Path, frames: usize, poses: usize) {
        std::fs::create_dir_all(dir.join("velodyne")).unwrap();
        let calib = "P2: 700 0 600 42 0 700 180 0 0 0 1 0\nTr: 0 -1 0 0 0 0 -1 -0.08 1 0 0 -0.27\n";
        write_atomic(&dir.join("calib.txt"), calib.as_bytes()).unwrap();
        for i in 0..frames {
            let p = LidarPoint { x: i as f32, y: 0.0, z: 0.0, intensity: 0.5 };
            write_velodyne(&dir.join("velodyne").join(format!("{i:06}.bin")), &[p]).unwrap();
        }
        write_poses(&dir.join("poses.txt"), &vec![Pose::identity(); poses]).unwrap();
    }

    #[test]
    fn frames_follow_the_files_and_short_pose_files_are_refused() {
        let root = tempfile::tempdir().unwrap();
        write_sequence(&root.path().join("03"), 3, 3);
        let seq = Sequence::open(&root.path().join("03"), None).unwrap();
        assert_eq!(seq.frame_indices, vec![0, 1, 2]);
        let frame = seq.frame(2).unwrap();
        assert_eq!(frame.read_points().unwrap()[0].x, 2.0);
        assert!(frame.image_path.ends_with("image_2/000002.png"));
        // camera_from_lidar = [I | (42/700, 0, 0)] · Tr
        assert!((frame.camera_from_lidar.translation().x - 0.06).abs() < 1e-12);
        assert!(seq.frame(3).unwrap_err().to_string().contains("no frame 3"));
        write_sequence(&root.path().join("04"), 3, 2);
        let err = discover_sequences(root.path()).unwrap_err().to_string();
        assert!(err.contains("poses.txt") && err.contains("has 2 poses"), "{err}");
        let empty = tempfile::tempdir().unwrap();
        assert!(discover_sequences(empty.path()).unwrap_err().to_string().contains("no KITTI sequence"));
    }

    #[test]
    fn the_map_frame_is_the_lidar_at_frame_0_and_conversions_invert() {
        let root = tempfile::tempdir().unwrap();
        let dir = root.path().join("00");
        write_sequence(&dir, 2, 2);
        let mut seq = Sequence::open(&dir, None).unwrap();
        // Frame 1: cam0 moved 2 m forward (cam0 z) and turned 10° about cam0 y.
        let turn = Pose::from_rt(*nalgebra::Rotation3::from_axis_angle(&nalgebra::Vector3::y_axis(), 10f64.to_radians()).matrix(), nalgebra::Vector3::new(0.0, 0.0, 2.0));
        seq.poses = Some(vec![Pose::identity(), turn]);
        assert!((seq.map_from_lidar(0).unwrap().matrix() - Pose::identity().matrix()).abs().max() < 1e-12);
        let m1 = seq.map_from_lidar(1).unwrap();
        // In the LiDAR's axes that is about 2 m along +x (forward; the turn is about cam0, not
        // the LiDAR, hence the few cm sideways), no height change, a turn about z.
        let t = m1.translation();
        assert!((t.x - 2.0).abs() < 0.01 && t.y.abs() < 0.05 && t.z.abs() < 1e-9, "{m1:?}");
        assert!((m1.rotation()[(2, 2)] - 1.0).abs() < 1e-12);
        // Truth of image_2 and its poses.txt line are each other's inverse.
        let truth = seq.camera_from_map(1).unwrap();
        assert!((seq.world_from_cam0(&truth).unwrap().matrix() - turn.matrix()).abs().max() < 1e-12);
        let expected = seq.calib.color_camera_from_lidar().unwrap().compose(&m1.inverse());
        assert!((truth.matrix() - expected.matrix()).abs().max() < 1e-12);
        // A scan point moves with its frame.
        let p = seq.scan_in_map_frame(1).unwrap()[0];
        let q = m1.transform(&nalgebra::Point3::new(1.0, 0.0, 0.0));
        assert!((p.x as f64 - q.x).abs() < 1e-5 && (p.y as f64 - q.y).abs() < 1e-5);
        // times.txt: absent → None; short → an error naming the file.
        assert!(seq.times().unwrap().is_none());
        std::fs::write(dir.join("times.txt"), "0.0\n").unwrap();
        assert!(seq.times().unwrap_err().to_string().contains("times.txt"));
        std::fs::write(dir.join("times.txt"), "0.0\n0.103\n").unwrap();
        assert_eq!(seq.times().unwrap().unwrap(), vec![0.0, 0.103]);
    }
}
