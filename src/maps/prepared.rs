//! A map region ready for localization: the contract's N-point sample of the stored cloud and its
//! point embeddings. It does not depend on any image, so it is computed once per region and model
//! and then cached in memory (`cache`) and on disk (`embeddings`).

use anyhow::{Result, bail};
use nalgebra::Point3;
use rand::Rng;
use rand::SeedableRng;
use rand::seq::SliceRandom;
use rand_chacha::ChaCha8Rng;

use crate::model::{Backend, Points};

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
    /// The raw intensity of each of `points`, kept only where the features may be computed again
    /// from the points (a tiled region's crop, `Maps::reencode`, when its tiles hold intensity:
    /// those of a model that reads it); `None` elsewhere (a whole region's features are computed
    /// once, and a crop without it is encoded as a cloud without intensity).
    pub intensity: Option<Vec<f32>>,
}

impl PreparedMap {
    /// Memory held, for the cache's byte budget.
    pub fn size_bytes(&self) -> usize {
        self.points.len() * 12 + self.features.len() * 4 + self.intensity.as_ref().map_or(0, |i| i.len() * 4) + std::mem::size_of::<Self>()
    }

    /// The points as the point encoder's input, with their intensity when kept.
    pub fn input(&self) -> Points<'_> {
        Points::new(&self.points, self.intensity.as_deref())
    }
}

/// Samples the model's N points from a cloud (map frame; [`sample_indices`]) and runs the point
/// encoder on them, each with its own intensity when the cloud has it (read by a model whose
/// manifest names `intensity_rank`, ignored by others).
/// Errors: an intensity that is not one value per point, no finite point, the encoder's.
pub fn prepare_map(backend: &mut dyn Backend, cloud: Points<'_>) -> Result<PreparedMap> {
    cloud.check()?;
    let n = backend.manifest().points.num_points;
    let chosen = sample_indices(cloud.xyz, n)?;
    let points: Vec<[f32; 3]> = chosen.iter().map(|&i| cloud.xyz[i]).collect();
    let intensity: Option<Vec<f32>> = cloud.intensity.map(|values| chosen.iter().map(|&i| values[i]).collect());
    let features = backend.encode_points(Points::new(&points, intensity.as_deref()))?;
    let pivot = centroid(&points);
    let source_points = cloud.xyz.iter().filter(|p| p.iter().all(|v| v.is_finite())).count();
    Ok(PreparedMap { points, features, pivot, source_points, intensity: None })
}

/// The contract's sampling: a ChaCha8(seed 0) permutation of the finite points, first `n` of it;
/// a cloud smaller than `n` is filled by drawing with replacement from the same stream.
pub fn sample_points(cloud: &[[f32; 3]], n: usize) -> Result<Vec<[f32; 3]>> {
    Ok(sample_indices(cloud, n)?.into_iter().map(|i| cloud[i]).collect())
}

/// [`sample_points`] as indices into `cloud`, so that anything else per point (its intensity)
/// can follow the points.
pub fn sample_indices(cloud: &[[f32; 3]], n: usize) -> Result<Vec<usize>> {
    let finite: Vec<usize> = (0..cloud.len()).filter(|&i| cloud[i].iter().all(|v| v.is_finite())).collect();
    if finite.is_empty() {
        bail!("the point cloud has no finite points");
    }
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let mut order: Vec<usize> = (0..finite.len()).collect();
    order.shuffle(&mut rng);
    let mut out: Vec<usize> = order.iter().take(n).map(|&k| finite[k]).collect();
    while out.len() < n {
        out.push(finite[rng.random_range(0..finite.len())]);
    }
    Ok(out)
}

/// Each value's mid-rank among `values`: (the number of values below it + half the number equal
/// to it, itself included) / N, as f32 (computed in f64), so in (0, 1); a constant reads 0.5
/// everywhere, and an empty input gives an empty output. What a point encoder whose manifest
/// names `intensity_rank` reads beside x, y, z, over its N input points: rig-independent (any
/// increasing rescaling of a sensor's intensity leaves it unchanged). A non-finite value is read
/// as 0, as `training/cmr/data.py::read_scan` reads it, and −0 equals 0. The twin of
/// `training/cmr/data.py::intensity_rank`, pinned by `fixtures/conventions.json`.
pub fn intensity_rank(values: &[f32]) -> Vec<f32> {
    let clean = |v: f32| if v.is_finite() { v + 0.0 } else { 0.0 };
    let mut sorted: Vec<f32> = values.iter().map(|&v| clean(v)).collect();
    sorted.sort_unstable_by(f32::total_cmp);
    let n = values.len() as f64;
    values
        .iter()
        .map(|&v| {
            let v = clean(v);
            let below = sorted.partition_point(|&x| x < v);
            let upto = sorted.partition_point(|&x| x <= v);
            ((below as f64 + 0.5 * (upto - below) as f64) / n) as f32
        })
        .collect()
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

    /// The indices follow the same draws as the points, skipping non-finite points, and the
    /// sample is the one this function gave before it kept indices (pinned values).
    #[test]
    fn sample_indices_are_the_sampled_points() {
        let mut cloud: Vec<[f32; 3]> = (0..12).map(|i| [i as f32, 0.5 * i as f32, 1.0]).collect();
        cloud[3][1] = f32::NAN;
        cloud[7][2] = f32::INFINITY;
        for n in [4, 10, 25] {
            let indices = sample_indices(&cloud, n).unwrap();
            assert!(indices.iter().all(|&i| i != 3 && i != 7));
            let points = sample_points(&cloud, n).unwrap();
            assert_eq!(points, indices.iter().map(|&i| cloud[i]).collect::<Vec<_>>());
            // The former implementation: a permutation of the finite points themselves.
            let finite: Vec<[f32; 3]> = cloud.iter().copied().filter(|p| p.iter().all(|v| v.is_finite())).collect();
            let mut rng = ChaCha8Rng::seed_from_u64(0);
            let mut order: Vec<usize> = (0..finite.len()).collect();
            order.shuffle(&mut rng);
            let mut before: Vec<[f32; 3]> = order.iter().take(n).map(|&i| finite[i]).collect();
            while before.len() < n {
                before.push(finite[rng.random_range(0..finite.len())]);
            }
            assert_eq!(points.iter().map(|p| p.map(f32::to_bits)).collect::<Vec<_>>(), before.iter().map(|p| p.map(f32::to_bits)).collect::<Vec<_>>());
        }
    }

    #[test]
    fn intensity_rank_is_the_mid_rank() {
        assert_eq!(intensity_rank(&[]), Vec::<f32>::new());
        assert_eq!(intensity_rank(&[7.0; 5]), vec![0.5; 5]);
        assert_eq!(intensity_rank(&[3.0, 1.0, 2.0, 2.0]), vec![0.875, 0.125, 0.5, 0.5]);
        // Non-finite reads 0, and −0 equals 0.
        assert_eq!(intensity_rank(&[f32::NAN, 0.0, -0.0, 1.0]), vec![0.375, 0.375, 0.375, 0.875]);
        // Any increasing rescaling leaves it unchanged.
        let v = [0.3f32, 0.05, 0.9, 0.3, 0.0, 0.61];
        assert_eq!(intensity_rank(&v), intensity_rank(&v.map(|x| 255.0 * x + 4.0)));
    }
}
