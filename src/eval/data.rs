//! Turning a KITTI-odometry directory plus the frozen perturbations into evaluation cases,
//! through the project's one KITTI reader (`crate::kitti`).

use std::collections::HashMap;
use std::path::Path;

use anyhow::{Context, Result, bail};

use crate::maps::{centroid, sample_points};
use crate::kitti::{Sequence, discover_sequences};

use super::methods::EvalCase;
use super::perturbations::Perturbation;

/// The sequences of a dataset, by name.
pub struct Dataset {
    sequences: HashMap<String, Sequence>,
    order: Vec<String>,
}

impl Dataset {
    pub fn open(root: &Path) -> Result<Self> {
        let found = discover_sequences(root).with_context(|| format!("reading KITTI-odometry data under {}", root.display()))?;
        if found.is_empty() {
            bail!("no KITTI-odometry sequence under {}", root.display());
        }
        let order = found.iter().map(|s| s.name.clone()).collect();
        let sequences = found.into_iter().map(|s| (s.name.clone(), s)).collect();
        Ok(Dataset { sequences, order })
    }

    /// Every (sequence, frame) in order, taking every `stride`-th frame, at most `limit`.
    pub fn frames(&self, stride: usize, limit: Option<usize>) -> Vec<(String, usize)> {
        let all = self
            .order
            .iter()
            .flat_map(|name| self.sequences[name].frame_indices.iter().map(move |&i| (name.clone(), i)))
            .step_by(stride.max(1));
        match limit {
            Some(n) => all.take(n).collect(),
            None => all.collect(),
        }
    }

    /// Loads one case: the scan moved by Q into the map frame (with each point's intensity), its
    /// N-point sample, the image.
    pub fn case(&self, perturbation: &Perturbation, num_points: usize) -> Result<EvalCase> {
        let sequence = self
            .sequences
            .get(&perturbation.sequence)
            .with_context(|| format!("the perturbation file names sequence {:?}, which the data does not have", perturbation.sequence))?;
        let frame = sequence
            .frame(perturbation.frame)
            .with_context(|| format!("sequence {} has no frame {}", perturbation.sequence, perturbation.frame))?;
        let q = perturbation.map_from_lidar();
        let scan: Vec<_> = frame.read_points()?.into_iter().filter(|p| p.x.is_finite() && p.y.is_finite() && p.z.is_finite()).collect();
        let map_cloud: Vec<[f32; 3]> = scan
            .iter()
            .map(|p| {
                let m = q.transform(&nalgebra::Point3::new(p.x as f64, p.y as f64, p.z as f64));
                [m.x as f32, m.y as f32, m.z as f32]
            })
            .collect();
        let map_intensity: Vec<f32> = scan.iter().map(|p| p.intensity).collect();
        let map_points = sample_points(&map_cloud, num_points)?;
        Ok(EvalCase {
            pivot: centroid(&map_points),
            map_points,
            map_cloud,
            map_intensity: Some(map_intensity),
            image: frame.read_image()?,
            intrinsics: frame.intrinsics,
            initial: frame.camera_from_lidar,
            truth: perturbation.truth(&frame.camera_from_lidar),
            perturbation: perturbation.clone(),
        })
    }
}
