//! A map region ready for localization: the contract's N-point sample of the stored cloud and its
//! point embeddings. It does not depend on any image, so it is computed once per region and model
//! and then cached in memory (`cache`) and on disk (`embeddings`).

use anyhow::{Result, bail};
use nalgebra::Point3;
use rand::Rng;
use rand::SeedableRng;
use rand::seq::SliceRandom;
use rand_chacha::ChaCha8Rng;

use crate::model::Backend;

#[derive(Debug, Clone)]
pub struct PreparedMap {
    /// The N sampled points, map frame, metres.
    pub points: Vec<[f32; 3]>,
    /// Point features [N, D], row-major.
    pub features: Vec<f32>,
    /// Centroid of the sampled points (map frame): the pivot of every rotation step.
    pub pivot: Point3<f64>,
    /// How many finite points the source cloud had.
    pub source_points: usize,
}

impl PreparedMap {
    /// Memory held, for the cache's byte budget.
    pub fn size_bytes(&self) -> usize {
        self.points.len() * 12 + self.features.len() * 4 + std::mem::size_of::<Self>()
    }
}

/// Samples the model's N points from a cloud (map frame) and runs the point encoder on them.
pub fn prepare_map(backend: &mut dyn Backend, cloud: &[[f32; 3]]) -> Result<PreparedMap> {
    let n = backend.manifest().points.num_points;
    let points = sample_points(cloud, n)?;
    let features = backend.encode_points(&points)?;
    let pivot = centroid(&points);
    let source_points = cloud.iter().filter(|p| p.iter().all(|v| v.is_finite())).count();
    Ok(PreparedMap { points, features, pivot, source_points })
}

/// The contract's sampling: a ChaCha8(seed 0) permutation of the finite points, first `n` of it;
/// a cloud smaller than `n` is filled by drawing with replacement from the same stream.
pub fn sample_points(cloud: &[[f32; 3]], n: usize) -> Result<Vec<[f32; 3]>> {
    let finite: Vec<[f32; 3]> = cloud.iter().copied().filter(|p| p.iter().all(|v| v.is_finite())).collect();
    if finite.is_empty() {
        bail!("the point cloud has no finite points");
    }
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let mut order: Vec<usize> = (0..finite.len()).collect();
    order.shuffle(&mut rng);
    let mut out: Vec<[f32; 3]> = order.iter().take(n).map(|&i| finite[i]).collect();
    while out.len() < n {
        out.push(finite[rng.random_range(0..finite.len())]);
    }
    Ok(out)
}

/// Mean of the points, in f64.
pub fn centroid(points: &[[f32; 3]]) -> Point3<f64> {
    let mut sum = [0f64; 3];
    for p in points {
        for c in 0..3 {
            sum[c] += p[c] as f64;
        }
    }
    let n = points.len().max(1) as f64;
    Point3::new(sum[0] / n, sum[1] / n, sum[2] / n)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sampling_is_deterministic_and_fills_small_clouds() {
        let cloud: Vec<[f32; 3]> = (0..10).map(|i| [i as f32, 0.0, 0.0]).collect();
        let a = sample_points(&cloud, 25).unwrap();
        assert_eq!(a, sample_points(&cloud, 25).unwrap());
        assert_eq!(a.len(), 25);
        let mut first: Vec<f32> = a[..10].iter().map(|p| p[0]).collect();
        first.sort_by(f32::total_cmp);
        assert_eq!(first, (0..10).map(|i| i as f32).collect::<Vec<_>>(), "every point once before refilling");
        assert!(sample_points(&[[f32::NAN, 0.0, 0.0]], 4).is_err());
    }
}
