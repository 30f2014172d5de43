//! The agent's observation, built in Rust exactly as the model contract describes.
//!
//! state_2d [2D, GH, GW]: the image features, then F_k = the scatter-MEAN of the point features of
//! every sampled point that projects (current pose, crop intrinsics) into the model input, cell
//! (row, col) = (floor((v+0.5)/stride), floor((u+0.5)/stride)); empty cells stay 0.
//! state_3d [M, 5]: for the first M sampled points, xyz in the current camera frame divided by
//! the manifest's scale, sigmoid(frustum logit), and 1/0 = inside the current frustum.
//!
//! The same scatter also yields the pose's alignment score ([`alignment`]), which the
//! multi-start search ranks hypotheses by.

use nalgebra::Point3;

use crate::geometry::{Intrinsics, Pose};
use crate::model::Manifest;

/// The sizes the state builder needs, taken once from the manifest.
#[derive(Debug, Clone, Copy)]
pub struct StateLayout {
    pub dim: usize,
    pub stride: usize,
    pub grid_height: usize,
    pub grid_width: usize,
    pub image_width: u32,
    pub image_height: u32,
    pub num_state_points: usize,
    pub xyz_scale_m: f64,
}

impl StateLayout {
    pub fn from_manifest(m: &Manifest) -> Self {
        Self {
            dim: m.features.dim,
            stride: m.features.stride,
            grid_height: m.features.grid_height,
            grid_width: m.features.grid_width,
            image_width: m.image.width,
            image_height: m.image.height,
            num_state_points: m.points.num_state_points,
            xyz_scale_m: m.points.state_xyz_scale_m,
        }
    }

    pub fn cells(&self) -> usize {
        self.grid_height * self.grid_width
    }

    pub fn image_feature_len(&self) -> usize {
        self.dim * self.cells()
    }

    pub fn state_2d_len(&self) -> usize {
        2 * self.image_feature_len()
    }

    pub fn state_3d_len(&self) -> usize {
        self.num_state_points * 5
    }

    /// The feature cell a camera-frame point falls into, or `None` outside the frustum.
    #[inline]
    pub fn cell_of(&self, k: &Intrinsics, p_cam: &Point3<f64>) -> Option<usize> {
        // Same test as `Intrinsics::in_frustum`, with the projection computed once.
        let (u, v) = k.project(p_cam)?;
        if !(u >= -0.5 && v >= -0.5 && u < self.image_width as f64 - 0.5 && v < self.image_height as f64 - 0.5) {
            return None;
        }
        let s = self.stride as f64;
        let row = (((v + 0.5) / s).floor() as usize).min(self.grid_height - 1);
        let col = (((u + 0.5) / s).floor() as usize).min(self.grid_width - 1);
        Some(row * self.grid_width + col)
    }
}

/// Reusable buffers so a step allocates nothing.
#[derive(Default)]
pub struct ScatterScratch {
    /// Per-cell feature sums, cell-major; all zero between calls.
    sums: Vec<f32>,
    /// Per-cell point counts; all zero between calls.
    counts: Vec<u32>,
    /// Cells that received a point in this call.
    touched: Vec<u32>,
}

/// Writes one state into `state_2d` (len `state_2d_len`) and `state_3d` (len `state_3d_len`).
/// Returns the alignment score of `camera_from_map` (see [`alignment`]), which falls out of the
/// scatter at no extra cost.
#[allow(clippy::too_many_arguments)]
pub fn write_state(
    layout: &StateLayout,
    points: &[[f32; 3]],
    point_features: &[f32],
    frustum_probs: &[f32],
    image_features: &[f32],
    k: &Intrinsics,
    camera_from_map: &Pose,
    scratch: &mut ScatterScratch,
    state_2d: &mut [f32],
    state_3d: &mut [f32],
) -> f32 {
    let scale = layout.xyz_scale_m;
    let m = layout.num_state_points.min(points.len());
    scatter(layout, points, point_features, k, camera_from_map, scratch, |i, p_cam, in_view| {
        if i < m {
            let row = &mut state_3d[i * 5..(i + 1) * 5];
            row[0] = (p_cam.x / scale) as f32;
            row[1] = (p_cam.y / scale) as f32;
            row[2] = (p_cam.z / scale) as f32;
            row[3] = frustum_probs[i];
            row[4] = if in_view { 1.0 } else { 0.0 };
        }
    });
    let (image_part, points_part) = state_2d.split_at_mut(layout.image_feature_len());
    image_part.copy_from_slice(image_features);
    points_part.fill(0.0);
    drain(layout, image_features, scratch, Some(points_part))
}

/// How well a pose explains the image: the mean, over the sampled points in view, of the dot
/// product between a point's feature and the image feature of the cell it projects to; −1 when
/// no point is in view. Both embeddings are unit vectors trained to agree at true
/// correspondences, so the true pose scores highest; the multi-start search (`super::search`)
/// uses it to choose among hypotheses. `training/cmr/state.py::alignment` is its twin.
pub fn alignment(
    layout: &StateLayout,
    points: &[[f32; 3]],
    point_features: &[f32],
    image_features: &[f32],
    k: &Intrinsics,
    camera_from_map: &Pose,
    scratch: &mut ScatterScratch,
) -> f32 {
    scatter(layout, points, point_features, k, camera_from_map, scratch, |_, _, _| {});
    drain(layout, image_features, scratch, None)
}

/// One pass over the points: transform with a plain matrix (cheaper than the quaternion),
/// project once, and add each in-view point's feature to its cell's sum. `each` sees every point
/// with its camera-frame position and whether it is in view.
#[allow(clippy::too_many_arguments)]
fn scatter(
    layout: &StateLayout,
    points: &[[f32; 3]],
    point_features: &[f32],
    k: &Intrinsics,
    camera_from_map: &Pose,
    scratch: &mut ScatterScratch,
    mut each: impl FnMut(usize, &Point3<f64>, bool),
) {
    let (d, cells) = (layout.dim, layout.cells());
    debug_assert_eq!(point_features.len(), points.len() * d);
    // The buffers stay zeroed between calls; `drain` resets only the touched cells, so a step
    // costs work proportional to the points in view, not to the grid size.
    if scratch.counts.len() != cells || scratch.sums.len() != cells * d {
        scratch.sums = vec![0.0; cells * d];
        scratch.counts = vec![0; cells];
    }
    scratch.touched.clear();
    let r = camera_from_map.rotation();
    let t = camera_from_map.translation();
    for (i, p) in points.iter().enumerate() {
        let (x, y, z) = (p[0] as f64, p[1] as f64, p[2] as f64);
        let p_cam = Point3::new(
            r[(0, 0)] * x + r[(0, 1)] * y + r[(0, 2)] * z + t.x,
            r[(1, 0)] * x + r[(1, 1)] * y + r[(1, 2)] * z + t.y,
            r[(2, 0)] * x + r[(2, 1)] * y + r[(2, 2)] * z + t.z,
        );
        let cell = layout.cell_of(k, &p_cam);
        if let Some(cell) = cell {
            if scratch.counts[cell] == 0 {
                scratch.touched.push(cell as u32);
            }
            scratch.counts[cell] += 1;
            let sum = &mut scratch.sums[cell * d..(cell + 1) * d];
            for (s, f) in sum.iter_mut().zip(&point_features[i * d..(i + 1) * d]) {
                *s += f;
            }
        }
        each(i, &p_cam, cell.is_some());
    }
}

/// Ends a `scatter`: writes the per-cell means into `means` ([D, cells], channel-major) when
/// given, zeroes the scratch again, and returns the alignment score. Σ over points of
/// f_i · I(cell_i) equals Σ over cells of (Σ f_i) · I(cell), so the score needs only the sums.
fn drain(layout: &StateLayout, image_features: &[f32], scratch: &mut ScatterScratch, mut means: Option<&mut [f32]>) -> f32 {
    let (d, cells) = (layout.dim, layout.cells());
    // Channel-major outputs: visiting the touched cells in ascending order per channel keeps the
    // reads of `image_features` and the writes of `means` moving forward through memory.
    scratch.touched.sort_unstable();
    let mut in_view = 0u64;
    for &cell in &scratch.touched {
        in_view += scratch.counts[cell as usize] as u64;
    }
    let mut dot = 0f64;
    for c in 0..d {
        let image = &image_features[c * cells..(c + 1) * cells];
        let mut channel = 0f64;
        match means.as_deref_mut() {
            Some(means) => {
                let out = &mut means[c * cells..(c + 1) * cells];
                for &cell in &scratch.touched {
                    let cell = cell as usize;
                    let s = scratch.sums[cell * d + c];
                    channel += (s * image[cell]) as f64;
                    out[cell] = s / scratch.counts[cell] as f32;
                }
            }
            None => {
                for &cell in &scratch.touched {
                    let cell = cell as usize;
                    channel += (scratch.sums[cell * d + c] * image[cell]) as f64;
                }
            }
        }
        dot += channel;
    }
    for &cell in &scratch.touched {
        let cell = cell as usize;
        scratch.sums[cell * d..(cell + 1) * d].fill(0.0);
        scratch.counts[cell] = 0;
    }
    if in_view == 0 { -1.0 } else { (dot / in_view as f64) as f32 }
}

pub fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn layout() -> StateLayout {
        StateLayout {
            dim: 2,
            stride: 4,
            grid_height: 2,
            grid_width: 3,
            image_width: 12,
            image_height: 8,
            num_state_points: 3,
            xyz_scale_m: 10.0,
        }
    }

    #[test]
    fn scatter_mean_averages_features_per_cell_and_leaves_empty_cells_zero() {
        let layout = layout();
        let k = Intrinsics { fx: 10.0, fy: 10.0, cx: 0.0, cy: 0.0 };
        // (u, v) = (10 x / z, 10 y / z) with z = 10: u = x, v = y.
        let points = [[1.0f32, 1.0, 10.0], [2.0, 2.0, 10.0], [9.0, 5.0, 10.0], [50.0, 0.0, 10.0], [0.0, 0.0, -3.0]];
        let features = [1.0f32, 2.0, 3.0, 4.0, 10.0, 20.0, 7.0, 7.0, 9.0, 9.0];
        let probs = [0.1f32, 0.2, 0.3, 0.4, 0.5];
        let image = vec![0.5f32; layout.image_feature_len()];
        let mut s2 = vec![f32::NAN; layout.state_2d_len()];
        let mut s3 = vec![f32::NAN; layout.state_3d_len()];
        let mut scratch = ScatterScratch::default();
        let score = write_state(&layout, &points, &features, &probs, &image, &k, &Pose::identity(), &mut scratch, &mut s2, &mut s3);
        // Points 0-2 are in view: (0.5 (1 + 2) + 0.5 (3 + 4) + 0.5 (10 + 20)) / 3.
        assert!((score - 20.0 / 3.0).abs() < 1e-6, "{score}");
        assert_eq!(alignment(&layout, &points, &features, &image, &k, &Pose::identity(), &mut scratch), score);
        // A second call with the same scratch buffers gives the same state.
        let (first_2d, first_3d) = (s2.clone(), s3.clone());
        write_state(&layout, &points, &features, &probs, &image, &k, &Pose::identity(), &mut scratch, &mut s2, &mut s3);
        assert_eq!((&first_2d, &first_3d), (&s2, &s3));
        let cells = layout.cells();
        assert!(s2[..2 * cells].iter().all(|v| *v == 0.5));
        let f = &s2[2 * cells..];
        // Points 0 and 1 share cell (0, 0); point 2 is at (u, v) = (9, 5): cell (1, 2).
        assert_eq!((f[0], f[cells]), (2.0, 3.0));
        assert_eq!((f[5], f[cells + 5]), (10.0, 20.0));
        assert_eq!(f.iter().filter(|v| **v != 0.0).count(), 4);
        assert_eq!(&s3[..5], &[0.1, 0.1, 1.0, 0.1, 1.0]);
        assert_eq!(s3[14], 1.0);
        // Nothing in view: the worst score.
        let behind = Pose::from_rt(nalgebra::Matrix3::identity(), nalgebra::Vector3::new(0.0, 0.0, -100.0));
        assert_eq!(alignment(&layout, &points, &features, &image, &k, &behind, &mut scratch), -1.0);
    }

    #[test]
    fn cell_test_agrees_with_the_geometry_frustum() {
        use rand::{Rng, SeedableRng};
        let layout = StateLayout { grid_height: 40, grid_width: 128, image_width: 512, image_height: 160, ..layout() };
        let k = Intrinsics { fx: 359.4, fy: 359.4, cx: 249.8, cy: 78.1 };
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        for _ in 0..20000 {
            let p = Point3::new(rng.random_range(-30.0..30.0), rng.random_range(-5.0..5.0), rng.random_range(-2.0..40.0));
            assert_eq!(layout.cell_of(&k, &p).is_some(), k.in_frustum(&p, 512, 160), "{p:?}");
        }
    }

    #[test]
    fn frustum_edges_follow_the_geometry_convention() {
        let layout = layout();
        let k = Intrinsics { fx: 10.0, fy: 10.0, cx: 0.0, cy: 0.0 };
        assert_eq!(layout.cell_of(&k, &Point3::new(-0.5, -0.5, 10.0)), Some(0));
        assert_eq!(layout.cell_of(&k, &Point3::new(11.49, 7.49, 10.0)), Some(5));
        assert_eq!(layout.cell_of(&k, &Point3::new(11.5, 0.0, 10.0)), None);
        assert_eq!(layout.cell_of(&k, &Point3::new(0.0, 0.0, 0.05)), None);
    }
}

#[cfg(test)]
mod timing {
    use super::*;

    /// Manual timing, not a speed test: `cargo test --release --lib state_build_timing -- --ignored --nocapture`.
    #[test]
    #[ignore]
    fn state_build_timing() {
        use rand::{Rng, SeedableRng};
        let layout = StateLayout { dim: 64, stride: 4, grid_height: 40, grid_width: 128, image_width: 512, image_height: 160, num_state_points: 2048, xyz_scale_m: 10.0 };
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        let points: Vec<[f32; 3]> = (0..40960).map(|_| [rng.random_range(-40.0..40.0), rng.random_range(-40.0..40.0), rng.random_range(-2.0..3.0)]).collect();
        let features: Vec<f32> = (0..40960 * 64).map(|_| rng.random_range(-0.2..0.2)).collect();
        let probs = vec![0.5f32; 40960];
        let image = vec![0.1f32; layout.image_feature_len()];
        let k = Intrinsics { fx: 359.4, fy: 359.4, cx: 249.8, cy: 78.1 };
        let r = nalgebra::Matrix3::new(0.0, -1.0, 0.0, 0.0, 0.0, -1.0, 1.0, 0.0, 0.0);
        let pose = Pose::from_rt(r, nalgebra::Vector3::new(0.0, -0.08, -0.27));
        let mut s2 = vec![0f32; layout.state_2d_len()];
        let mut s3 = vec![0f32; layout.state_3d_len()];
        let mut scratch = ScatterScratch::default();
        // CPU time of this thread (the machine is shared, so wall time overstates the cost).
        let cpu_ms = || -> f64 {
            let stat = std::fs::read_to_string("/proc/thread-self/stat").unwrap_or_default();
            let fields: Vec<&str> = stat.rsplit(')').next().unwrap_or("").split_whitespace().collect();
            fields.get(11).and_then(|v| v.parse::<f64>().ok()).unwrap_or(f64::NAN) * 10.0
        };
        let (t, c) = (std::time::Instant::now(), cpu_ms());
        let reps = 200;
        for _ in 0..reps {
            write_state(&layout, &points, &features, &probs, &image, &k, &pose, &mut scratch, &mut s2, &mut s3);
        }
        println!(
            "write_state (N = 40960): {:.3} ms wall, {:.3} ms CPU per state",
            t.elapsed().as_secs_f64() * 1000.0 / reps as f64,
            (cpu_ms() - c) / reps as f64
        );
    }
}
