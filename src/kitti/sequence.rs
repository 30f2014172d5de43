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
}
