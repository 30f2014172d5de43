//! The agent's observation, built in Rust exactly as the model contract describes.
//!
//! The 2D half comes in the form the manifest's `state_2d` section names
//! (`model::State2dSpec`):
//! - features: [2D, GH, GW], the image features, then F_k = the scatter-MEAN of the point
//!   features of every sampled point that projects (current pose, crop intrinsics) into the model
//!   input, cell (row, col) = (floor((v+0.5)/stride), floor((u+0.5)/stride)); empty cells stay 0;
//! - correlation: [S + 1, GH, GW], what the agent makes of that pair before any learned layer
//!   (`training/cmr/models.py::Agent.correlate`): at each cell whose F_k is not zero, the cosine of
//!   F_k/|F_k| with the image feature s cells along the row (each row shift) or down the column
//!   (each column shift), 0 off the grid; then the occupancy (1 at those cells). Empty cells are 0.
//!
//! state_3d [M, 5]: for the first M sampled points, xyz in the current camera frame divided by
//! the manifest's scale, sigmoid(frustum logit), and 1/0 = inside the current frustum.
//!
//! The same scatter also yields the pose's alignment score ([`alignment`]), which the
//! multi-start search ranks hypotheses by.

use std::sync::Mutex;

use nalgebra::Point3;

use crate::geometry::{Intrinsics, MIN_DEPTH_M, Pose};
use crate::model::{MAX_CORRELATION_SHIFTS, Manifest};

/// The 2D half of the state the model reads (the manifest's `state_2d.form`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Form2d {
    Features,
    Correlation(Shifts),
}

/// The cell offsets of a correlation-form state: row shifts (along a row, in columns) first, then
/// column shifts (down a column, in rows), as the manifest lists them.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Shifts {
    values: [i16; MAX_CORRELATION_SHIFTS],
    rows: usize,
    columns: usize,
}

impl Shifts {
    /// Panics beyond [`MAX_CORRELATION_SHIFTS`] or ±32767 (a loaded manifest is checked for both).
    pub fn new(rows: &[i32], columns: &[i32]) -> Self {
        assert!(rows.len() + columns.len() <= MAX_CORRELATION_SHIFTS, "too many correlation shifts");
        let mut values = [0i16; MAX_CORRELATION_SHIFTS];
        for (v, s) in values.iter_mut().zip(rows.iter().chain(columns)) {
            *v = i16::try_from(*s).expect("shift fits the grid");
        }
        Self { values, rows: rows.len(), columns: columns.len() }
    }

    pub fn rows(&self) -> &[i16] {
        &self.values[..self.rows]
    }

    pub fn columns(&self) -> &[i16] {
        &self.values[self.rows..self.rows + self.columns]
    }

    /// Channels of the state: one per shift and the occupancy.
    pub fn channels(&self) -> usize {
        self.rows + self.columns + 1
    }
}

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
    pub form: Form2d,
}

impl StateLayout {
    pub fn from_manifest(m: &Manifest) -> Self {
        let spec = &m.state_2d;
        Self {
            dim: m.features.dim,
            stride: m.features.stride,
            grid_height: m.features.grid_height,
            grid_width: m.features.grid_width,
            image_width: m.image.width,
            image_height: m.image.height,
            num_state_points: m.points.num_state_points,
            xyz_scale_m: m.points.state_xyz_scale_m,
            form: if spec.is_features() { Form2d::Features } else { Form2d::Correlation(Shifts::new(&spec.row_shifts, &spec.column_shifts)) },
        }
    }

    pub fn cells(&self) -> usize {
        self.grid_height * self.grid_width
    }

    pub fn image_feature_len(&self) -> usize {
        self.dim * self.cells()
    }

    /// Values of one row of the 2D state.
    pub fn state_2d_len(&self) -> usize {
        match self.form {
            Form2d::Features => 2 * self.image_feature_len(),
            Form2d::Correlation(shifts) => shifts.channels() * self.cells(),
        }
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

/// One image's features in the layouts the state builder reads: channel-major [D, GH·GW] as the
/// image encoder returns them, and cell-major [GH·GW, D] (so a cell's feature is one contiguous
/// vector: the correlation form and the alignment score read it). Made once per request.
#[derive(Debug, Default)]
pub struct ImageGrid {
    pub channel_major: Vec<f32>,
    pub cell_major: Vec<f32>,
}

impl ImageGrid {
    pub fn new(layout: &StateLayout, channel_major: Vec<f32>) -> Self {
        let (d, cells) = (layout.dim, layout.cells());
        let mut cell_major = vec![0f32; d * cells];
        for (c, channel) in channel_major.chunks_exact(cells).enumerate() {
            for (cell, v) in channel.iter().enumerate() {
                cell_major[cell * d + c] = *v;
            }
        }
        Self { channel_major, cell_major }
    }
}

/// Reusable buffers so a step allocates nothing.
#[derive(Default)]
pub struct ScatterScratch {
    /// Per-cell feature sums, cell-major; all zero between calls.
    sums: Vec<f32>,
    /// Per-cell point counts; all zero between calls.
    counts: Vec<u32>,
    /// Cells that received a point in this call, ascending (`list_touched`).
    touched: Vec<u32>,
    /// Every point's cell (`OUT_OF_VIEW` outside the frustum).
    cells: Vec<u32>,
    /// (point index, cell) of the points in view, in point order.
    visible: Vec<(u32, u32)>,
    /// The alignment's per-channel sums (correlation form).
    channel_dots: Vec<f64>,
    /// One cell's unit point feature (correlation form).
    unit: Vec<f32>,
}

/// Scatter buffers for work on several threads at once (a batch's states, the polished choice's
/// climbs): [`ScratchPool::with`] lends one to a closure and takes it back when the closure
/// returns (a closure that panics keeps it, so a half-written buffer is never lent again).
#[derive(Default)]
pub struct ScratchPool(Mutex<Vec<ScatterScratch>>);

impl ScratchPool {
    /// Runs `work` with a buffer of the pool (a new one when all are lent).
    pub fn with<R>(&self, work: impl FnOnce(&mut ScatterScratch) -> R) -> R {
        let mut scratch = self.0.lock().expect("scratch pool").pop().unwrap_or_default();
        let out = work(&mut scratch);
        self.0.lock().expect("scratch pool").push(scratch);
        out
    }
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
    image: &ImageGrid,
    k: &Intrinsics,
    camera_from_map: &Pose,
    scratch: &mut ScatterScratch,
    state_2d: &mut [f32],
    state_3d: &mut [f32],
) -> f32 {
    let scale = layout.xyz_scale_m;
    let m = layout.num_state_points.min(points.len());
    scatter(layout, points, None, point_features, k, camera_from_map, scratch, m, |i, p_cam, in_view| {
        let row = &mut state_3d[i * 5..(i + 1) * 5];
        row[0] = (p_cam.x / scale) as f32;
        row[1] = (p_cam.y / scale) as f32;
        row[2] = (p_cam.z / scale) as f32;
        row[3] = frustum_probs[i];
        row[4] = if in_view { 1.0 } else { 0.0 };
    });
    match layout.form {
        Form2d::Features => {
            let (image_part, points_part) = state_2d.split_at_mut(layout.image_feature_len());
            image_part.copy_from_slice(&image.channel_major);
            points_part.fill(0.0);
            drain(layout, &image.channel_major, scratch, points_part)
        }
        Form2d::Correlation(shifts) => {
            state_2d.fill(0.0);
            write_correlation(layout, shifts, &image.cell_major, scratch, state_2d)
        }
    }
}

/// Ends a `scatter` in the correlation form: writes the 2D state into `out` [S + 1, cells],
/// which must be all zero, zeroes the scratch again and returns the alignment score, as `drain`
/// would (the same products summed in the same order), in one cell-major pass. Twin of
/// `Agent.correlate` in `training/cmr/models.py`: the per-cell mean, its norm n, occupancy n >
/// 1e-6, unit = mean / (n + 1e-6), and one dot product with a shifted image cell per shift (here
/// the mean and the unit vector are multiplications by the reciprocal, which moves the last bit).
fn write_correlation(layout: &StateLayout, shifts: Shifts, image_cells: &[f32], scratch: &mut ScatterScratch, out: &mut [f32]) -> f32 {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU has AVX2 (checked just above), all `correlate_avx2` requires.
        return unsafe { correlate_avx2(layout, shifts, image_cells, scratch, out) };
    }
    // SAFETY: `Portable` is plain Rust.
    unsafe {
        match layout.dim {
            64 => correlate_cells::<64, Portable>(layout, shifts, image_cells, scratch, out),
            _ => correlate_cells::<0, Portable>(layout, shifts, image_cells, scratch, out),
        }
    }
}

/// `correlate_cells` compiled for AVX2, with `Avx`'s dot products.
///
/// # Safety
/// The CPU must support AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn correlate_avx2(layout: &StateLayout, shifts: Shifts, image_cells: &[f32], scratch: &mut ScatterScratch, out: &mut [f32]) -> f32 {
    // SAFETY: AVX2 includes AVX, all `Avx` requires; the caller guarantees AVX2.
    unsafe {
        match layout.dim {
            64 => correlate_cells::<64, Avx>(layout, shifts, image_cells, scratch, out),
            _ => correlate_cells::<0, Avx>(layout, shifts, image_cells, scratch, out),
        }
    }
}

/// `write_correlation` for feature width `D` (0: `layout.dim`, not known at compile time) with
/// the dot products of `L` (every `Lanes` gives the same results, so every build answers alike).
///
/// # Safety
/// The CPU must support `L`'s instructions.
#[inline(always)]
unsafe fn correlate_cells<const D: usize, L: Lanes>(layout: &StateLayout, shifts: Shifts, image_cells: &[f32], scratch: &mut ScatterScratch, out: &mut [f32]) -> f32 {
    let (d, w, h, cells) = (layout.dim, layout.grid_width, layout.grid_height, layout.cells());
    let d = if D > 0 { D } else { d };
    debug_assert_eq!(d, layout.dim);
    debug_assert_eq!(image_cells.len(), d * cells);
    debug_assert_eq!(out.len(), shifts.channels() * cells);
    let ScatterScratch { sums, counts, touched, unit, channel_dots, .. } = scratch;
    // Ascending cells keep the writes to each output plane moving forward (and give the
    // alignment sums `drain`'s order).
    list_touched(touched, counts);
    unit.resize(d, 0.0);
    let unit = &mut unit[..d];
    let image_cell = |cell: usize| &image_cells[cell * d..(cell + 1) * d];
    let occupancy = shifts.channels() - 1;
    // The alignment's per-channel sums, each over the cells in ascending order, as in `drain`.
    channel_dots.clear();
    channel_dots.resize(d, 0.0);
    let mut in_view = 0u64;
    for &cell in touched.iter() {
        let cell = cell as usize;
        let count = counts[cell];
        in_view += count as u64;
        counts[cell] = 0;
        let sum = &mut sums[cell * d..(cell + 1) * d];
        add_cell_dots(channel_dots, sum, image_cell(cell));
        let per_point = 1.0 / count as f32;
        for (u, s) in unit.iter_mut().zip(sum.iter_mut()) {
            *u = *s * per_point;
            *s = 0.0;
        }
        // SAFETY (the three `L::dot`): the caller guarantees `L`'s instructions.
        let norm = unsafe { L::dot(unit, unit) }.sqrt();
        if !(norm > 1e-6) {
            continue;
        }
        let per_norm = 1.0 / (norm + 1e-6);
        unit.iter_mut().for_each(|u| *u *= per_norm);
        let (row, col) = (cell / w, cell % w);
        for (k, &s) in shifts.rows().iter().enumerate() {
            let other = col as isize + s as isize;
            if (0..w as isize).contains(&other) {
                out[k * cells + cell] = unsafe { L::dot(unit, image_cell(row * w + other as usize)) };
            }
        }
        for (k, &s) in shifts.columns().iter().enumerate() {
            let other = row as isize + s as isize;
            if (0..h as isize).contains(&other) {
                out[(shifts.rows().len() + k) * cells + cell] = unsafe { L::dot(unit, image_cell(other as usize * w + col)) };
            }
        }
        out[occupancy * cells + cell] = 1.0;
    }
    touched.clear();
    score_of(channel_dots, in_view)
}

/// The correlation's f32 dot product, in one order whatever the instructions: eight lanes, lane
/// j the sum of a[8k + j]·b[8k + j] over k ascending (each product rounded, then added: no fused
/// multiply-add), the lanes folded in halves, ((l0 + l4) + (l2 + l6)) + ((l1 + l5) + (l3 + l7)),
/// then the tail beyond a multiple of eight added in order. `Portable` and `Avx` give the same
/// bits (test `dot_products_agree_to_the_bit`).
trait Lanes {
    /// # Safety
    /// The CPU must support the implementation's instructions.
    unsafe fn dot(a: &[f32], b: &[f32]) -> f32;
}

/// `Lanes` in plain Rust (any CPU).
struct Portable;

impl Lanes for Portable {
    #[inline(always)]
    unsafe fn dot(a: &[f32], b: &[f32]) -> f32 {
        let n = a.len().min(b.len());
        let body = n / 8 * 8;
        let mut l = [0f32; 8];
        for (x, y) in a[..body].chunks_exact(8).zip(b[..body].chunks_exact(8)) {
            for j in 0..8 {
                l[j] += x[j] * y[j];
            }
        }
        let half = [l[0] + l[4], l[1] + l[5], l[2] + l[6], l[3] + l[7]];
        let mut sum = (half[0] + half[2]) + (half[1] + half[3]);
        for i in body..n {
            sum += a[i] * b[i];
        }
        sum
    }
}

/// `Lanes` in one 256-bit register (AVX). Inlined into `correlate_avx2`, which is compiled for
/// AVX2, so the intrinsics inline too.
#[cfg(target_arch = "x86_64")]
struct Avx;

#[cfg(target_arch = "x86_64")]
impl Lanes for Avx {
    #[inline(always)]
    unsafe fn dot(a: &[f32], b: &[f32]) -> f32 {
        use std::arch::x86_64::*;
        let n = a.len().min(b.len());
        let body = n / 8 * 8;
        // SAFETY: every load reads 8 floats at an offset + 8 <= body <= both lengths; the CPU
        // has AVX (the caller's guarantee).
        let mut sum = unsafe {
            let mut acc = _mm256_setzero_ps();
            let mut i = 0;
            while i < body {
                acc = _mm256_add_ps(acc, _mm256_mul_ps(_mm256_loadu_ps(a.as_ptr().add(i)), _mm256_loadu_ps(b.as_ptr().add(i))));
                i += 8;
            }
            // [l0 + l4, l1 + l5, l2 + l6, l3 + l7], then [h0 + h2, h1 + h3, ..], then the two.
            let half = _mm_add_ps(_mm256_castps256_ps128(acc), _mm256_extractf128_ps::<1>(acc));
            let quarter = _mm_add_ps(half, _mm_movehl_ps(half, half));
            _mm_cvtss_f32(_mm_add_ss(quarter, _mm_shuffle_ps::<1>(quarter, quarter)))
        };
        for i in body..n {
            sum += a[i] * b[i];
        }
        sum
    }
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
    image: &ImageGrid,
    k: &Intrinsics,
    camera_from_map: &Pose,
    scratch: &mut ScatterScratch,
) -> f32 {
    scatter(layout, points, None, point_features, k, camera_from_map, scratch, 0, |_, _, _| {});
    drain_score(layout, &image.cell_major, scratch)
}

/// [`alignment`] of a pose near the one a [`NearView`] was made for (within its reach): the same
/// score to the bit, projecting only the points the view kept.
pub fn alignment_near(
    layout: &StateLayout,
    near: &NearView,
    point_features: &[f32],
    image: &ImageGrid,
    k: &Intrinsics,
    camera_from_map: &Pose,
    scratch: &mut ScatterScratch,
) -> f32 {
    scatter(layout, &near.points, Some(&near.index), point_features, k, camera_from_map, scratch, 0, |_, _, _| {});
    drain_score(layout, &image.cell_major, scratch)
}

/// The points of a map that some pose near one could see: every point that is in view (crop
/// intrinsics `k`, the layout's input size) from a pose within `rotation_deg` (geodesic angle)
/// and `translation_m` (camera centre distance) of `camera_from_map`, and a few more, in map
/// order. Scoring poses there with [`alignment_near`] skips the projection of the points no such
/// pose sees (the polish scores tens of poses within its reach).
///
/// The test, in the centre pose's camera frame: a point seen from a pose within the reach lies
/// within the input's corner angle θ of that pose's optical axis, which is within `rotation_deg`
/// of the centre's, from a camera centre within `translation_m` of the centre's; so the point
/// lies within `translation_m` of the cone about the centre's axis with half-angle θ +
/// `rotation_deg` (plus 0.2° and 1 cm for rounding). Degenerate intrinsics keep every point.
pub struct NearView {
    points: Vec<[f32; 3]>,
    /// Each kept point's index in the map, ascending.
    index: Vec<u32>,
}

impl NearView {
    pub fn new(layout: &StateLayout, k: &Intrinsics, points: &[[f32; 3]], camera_from_map: &Pose, rotation_deg: f64, translation_m: f64) -> Self {
        let (w, h) = (layout.image_width as f64, layout.image_height as f64);
        // The largest |x / z| and |y / z| of a point in view (`cells_with`'s test).
        let a = (k.cx + 0.5).abs().max((w - 0.5 - k.cx).abs()) / k.fx.abs();
        let b = (k.cy + 0.5).abs().max((h - 0.5 - k.cy).abs()) / k.fy.abs();
        let half_angle = a.hypot(b).atan() + (rotation_deg + 0.2).to_radians();
        let reach = translation_m + 0.01;
        if !(half_angle.is_finite() && reach.is_finite()) || half_angle >= std::f64::consts::PI || points.len() > u32::MAX as usize {
            return Self { points: points.to_vec(), index: (0..points.len() as u32).collect() };
        }
        let (cos, sin) = (half_angle.cos(), half_angle.sin());
        let rows = matrix_rows(camera_from_map);
        let (mut kept, mut index) = (Vec::new(), Vec::new());
        for (i, p) in points.iter().enumerate() {
            let c = transform(&rows, p);
            // In the plane of the axis and the point: axial h, radial q; `outside` is the
            // distance beyond the cone's side (≤ 0 inside), `ahead` > 0 where that side, not the
            // apex, is the nearest part of the cone.
            let (h, q) = (c.z, (c.x * c.x + c.y * c.y).sqrt());
            let outside = q * cos - h * sin;
            let ahead = h * cos + q * sin;
            if outside <= 0.0 || (outside <= reach && ahead > 0.0) || h * h + q * q <= reach * reach {
                kept.push(*p);
                index.push(i as u32);
            }
        }
        Self { points: kept, index }
    }

    /// How many of the map's points the view kept.
    pub fn len(&self) -> usize {
        self.index.len()
    }

    pub fn is_empty(&self) -> bool {
        self.index.is_empty()
    }
}

/// Adds each in-view point's feature to its cell's sum. `each` sees the first `first` points
/// with their camera-frame position and whether they are in view. With `index`, `points` are
/// those map points (their indices in `point_features`, ascending).
#[allow(clippy::too_many_arguments)]
fn scatter(
    layout: &StateLayout,
    points: &[[f32; 3]],
    index: Option<&[u32]>,
    point_features: &[f32],
    k: &Intrinsics,
    camera_from_map: &Pose,
    scratch: &mut ScatterScratch,
    first: usize,
    mut each: impl FnMut(usize, &Point3<f64>, bool),
) {
    let (d, cells) = (layout.dim, layout.cells());
    debug_assert!(index.is_some() || point_features.len() == points.len() * d);
    // The buffers stay zeroed between calls; `drain`, `drain_score` or `write_correlation`
    // resets only the touched cells (found with one pass over the grid's counts).
    if scratch.counts.len() != cells || scratch.sums.len() != cells * d {
        scratch.sums = vec![0.0; cells * d];
        scratch.counts = vec![0; cells];
    }
    scratch.visible.clear();
    let rows = matrix_rows(camera_from_map);
    // Pass 1: where every point lands (no feature reads, vector lanes).
    scratch.cells.resize(points.len(), 0);
    cells_of(layout, k, &rows, points, &mut scratch.cells);
    for (i, p) in points.iter().take(first).enumerate() {
        each(i, &transform(&rows, p), scratch.cells[i] != OUT_OF_VIEW);
    }
    let in_view = scratch.cells.iter().enumerate().filter(|(_, c)| **c != OUT_OF_VIEW);
    match index {
        None => scratch.visible.extend(in_view.map(|(i, c)| (i as u32, *c))),
        Some(index) => scratch.visible.extend(in_view.map(|(i, c)| (index[i], *c))),
    }
    // Pass 2: add the features of the points in view, in point order (so every cell's sum is the
    // same as in one pass). The feature rows are scattered through a map-sized array, so the
    // rows a few points ahead are fetched while this one is added.
    let ScatterScratch { sums, counts, visible, .. } = scratch;
    accumulate(d, point_features, visible, sums, counts);
}

/// `scatter`'s pass 2: adds each visible point's feature row to its cell's sum, in point order,
/// and counts the points per cell. Compiled for AVX2 and AVX-512 too and chosen at run time: the
/// additions are element by element, so every build gives the same sums.
#[multiversion::multiversion(targets("x86_64+avx512f+avx512vl+avx512dq", "x86_64+avx2"))]
fn accumulate(d: usize, point_features: &[f32], visible: &[(u32, u32)], sums: &mut [f32], counts: &mut [u32]) {
    for (n, &(i, cell)) in visible.iter().enumerate() {
        if let Some(&(ahead, _)) = visible.get(n + PREFETCH_POINTS_AHEAD) {
            prefetch(&point_features[ahead as usize * d..(ahead as usize + 1) * d]);
        }
        let (i, cell) = (i as usize, cell as usize);
        counts[cell] += 1;
        for (s, f) in sums[cell * d..(cell + 1) * d].iter_mut().zip(&point_features[i * d..(i + 1) * d]) {
            *s += f;
        }
    }
}

/// `cells_of`'s mark for a point outside the view.
const OUT_OF_VIEW: u32 = u32::MAX;
const _: () = assert!(OUT_OF_VIEW == -1i32 as u32, "cells_with casts −1 to OUT_OF_VIEW");

/// [R | t] of a pose as three rows (`Pose::to_rows` without the last): a plain matrix is
/// cheaper to apply than the quaternion.
fn matrix_rows(pose: &Pose) -> [[f64; 4]; 3] {
    let [r0, r1, r2, _] = pose.to_rows();
    [r0, r1, r2]
}

/// A map point in the camera frame: `rows` = [R | t] of camera_from_map (`matrix_rows`).
#[inline(always)]
fn transform(rows: &[[f64; 4]; 3], p: &[f32; 3]) -> Point3<f64> {
    let (x, y, z) = (p[0] as f64, p[1] as f64, p[2] as f64);
    let row = |k: usize| rows[k][0] * x + rows[k][1] * y + rows[k][2] * z + rows[k][3];
    Point3::new(row(0), row(1), row(2))
}

/// The feature cell of every point (`OUT_OF_VIEW` outside the frustum), with the arithmetic of
/// `StateLayout::cell_of` written without branches so the compiler can use vector lanes; also
/// compiled for AVX2 and AVX-512 and chosen at run time. No fused multiply-adds (Rust does not
/// contract), so every build gives the same cells as `cell_of`.
fn cells_of(layout: &StateLayout, k: &Intrinsics, rows: &[[f64; 4]; 3], points: &[[f32; 3]], cells: &mut [u32]) {
    // Dividing by a power of two is multiplying by its reciprocal, to the bit (both are the
    // exact quotient, rounded once), and a multiplication is several times cheaper.
    if layout.stride.is_power_of_two() {
        cells_with::<true>(layout, k, rows, points, cells)
    } else {
        cells_with::<false>(layout, k, rows, points, cells)
    }
}

/// `cells_of`, dividing by the stride (`POW2` false) or multiplying by its exact reciprocal.
#[multiversion::multiversion(targets("x86_64+avx512f+avx512vl+avx512dq", "x86_64+avx2"))]
fn cells_with<const POW2: bool>(layout: &StateLayout, k: &Intrinsics, rows: &[[f64; 4]; 3], points: &[[f32; 3]], cells: &mut [u32]) {
    let (right, bottom) = (layout.image_width as f64 - 0.5, layout.image_height as f64 - 0.5);
    let (stride, per_stride) = (layout.stride as f64, 1.0 / layout.stride as f64);
    let cell = |x: f64| if POW2 { x * per_stride } else { x / stride };
    let (last_row, last_col) = ((layout.grid_height - 1) as f64, (layout.grid_width - 1) as f64);
    let width = layout.grid_width as f64;
    for (p, out) in points.iter().zip(cells.iter_mut()) {
        let c = transform(rows, p);
        let (u, v) = (k.fx * c.x / c.z + k.cx, k.fy * c.y / c.z + k.cy);
        let inside = c.z >= MIN_DEPTH_M && u >= -0.5 && v >= -0.5 && u < right && v < bottom;
        // In view, (u + 0.5) / stride is in [0, grid width]: clamping before the cast is the
        // same as `cell_of`'s cast then min. The cell index is formed in f64 (exact: below 2^31)
        // and chosen before one cast, so the loop keeps its vector lanes (a saturating `as`
        // cast per lane does not vectorise).
        let row = cell(v + 0.5).floor().clamp(0.0, last_row);
        let col = cell(u + 0.5).floor().clamp(0.0, last_col);
        let index = if inside { row * width + col } else { -1.0 };
        // SAFETY: `index` is −1 or a cell index below 2^31 (never NaN: a NaN coordinate fails
        // `inside`), so it fits an i32; −1 as u32 is OUT_OF_VIEW.
        *out = unsafe { index.to_int_unchecked::<i32>() } as u32;
    }
}

/// How many points in view ahead `scatter` asks for feature rows.
const PREFETCH_POINTS_AHEAD: usize = 6;

/// Asks the CPU to bring `row` into its caches (a hint: no effect on results; a no-op off x86-64).
#[inline(always)]
fn prefetch(row: &[f32]) {
    #[cfg(target_arch = "x86_64")]
    for line in row.chunks(16) {
        // SAFETY: `_mm_prefetch` only hints the cache about an address; it never faults, and the
        // pointer comes from a live slice.
        unsafe { std::arch::x86_64::_mm_prefetch::<{ std::arch::x86_64::_MM_HINT_T0 }>(line.as_ptr().cast()) };
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = row;
}

/// Ends a `scatter` in the features form: writes the per-cell means into `means` ([D, cells],
/// channel-major), zeroes the scratch again, and returns the alignment score as [`drain_score`]
/// does (the same products summed in the same order). Σ over points of f_i · I(cell_i) equals Σ
/// over cells of (Σ f_i) · I(cell), so the score needs only the sums.
fn drain(layout: &StateLayout, image_features: &[f32], scratch: &mut ScatterScratch, means: &mut [f32]) -> f32 {
    let (d, cells) = (layout.dim, layout.cells());
    list_touched(&mut scratch.touched, &scratch.counts);
    let mut in_view = 0u64;
    for &cell in &scratch.touched {
        in_view += scratch.counts[cell as usize] as u64;
    }
    // Channel-major outputs: visiting the touched cells in ascending order per channel keeps the
    // reads of `image_features` and the writes of `means` moving forward through memory.
    let mut dot = 0f64;
    for c in 0..d {
        let image = &image_features[c * cells..(c + 1) * cells];
        let out = &mut means[c * cells..(c + 1) * cells];
        let mut channel = 0f64;
        for &cell in &scratch.touched {
            let cell = cell as usize;
            let s = scratch.sums[cell * d + c];
            channel += (s * image[cell]) as f64;
            out[cell] = s / scratch.counts[cell] as f32;
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

/// Ends a `scatter` for the score alone: zeroes the scratch again and returns the alignment
/// score. Per channel, the products of the cell sums with the image features (`image_cells`,
/// cell-major) are summed in f64 over the cells in ascending order, then the channels in order:
/// `drain`'s sums, but one cell's sums and image features are read as two contiguous vectors.
#[multiversion::multiversion(targets("x86_64+avx512f+avx512vl+avx512dq", "x86_64+avx2"))]
fn drain_score(layout: &StateLayout, image_cells: &[f32], scratch: &mut ScatterScratch) -> f32 {
    let d = layout.dim;
    let ScatterScratch { sums, counts, touched, channel_dots, .. } = scratch;
    list_touched(touched, counts);
    channel_dots.clear();
    channel_dots.resize(d, 0.0);
    let mut in_view = 0u64;
    for &cell in touched.iter() {
        let cell = cell as usize;
        in_view += counts[cell] as u64;
        counts[cell] = 0;
        let sum = &mut sums[cell * d..(cell + 1) * d];
        add_cell_dots(channel_dots, sum, &image_cells[cell * d..(cell + 1) * d]);
        sum.fill(0.0);
    }
    touched.clear();
    score_of(channel_dots, in_view)
}

/// Adds one cell's products, feature sum × image feature, to the alignment's per-channel sums
/// (each product rounded in f32, then added in f64): the order `drain` sums them in, per channel
/// over the cells in ascending order.
#[inline(always)]
fn add_cell_dots(channel_dots: &mut [f64], sum: &[f32], image_cell: &[f32]) {
    for ((acc, s), i) in channel_dots.iter_mut().zip(sum).zip(image_cell) {
        *acc += (s * i) as f64;
    }
}

/// The alignment score from its per-channel sums (channels in order) over `in_view` points; −1
/// with none in view.
fn score_of(channel_dots: &[f64], in_view: u64) -> f32 {
    if in_view == 0 { -1.0 } else { (channel_dots.iter().fold(0f64, |a, b| a + b) / in_view as f64) as f32 }
}

/// Lists the touched cells (count > 0) in ascending order: one pass over the grid's counts,
/// cheaper than collecting them during the scatter and sorting the thousands a real frame touches.
fn list_touched(touched: &mut Vec<u32>, counts: &[u32]) {
    touched.clear();
    touched.extend(counts.iter().enumerate().filter(|(_, n)| **n != 0).map(|(cell, _)| cell as u32));
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
            form: Form2d::Features,
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
        let image = ImageGrid::new(&layout, vec![0.5f32; layout.image_feature_len()]);
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
    fn correlation_form_correlates_unit_cell_means_with_shifted_image_cells() {
        // Grid 2 x 3, D = 2; shifts: one cell right along the row, one row down the column.
        let layout = StateLayout { form: Form2d::Correlation(Shifts::new(&[1], &[1])), ..layout() };
        let k = Intrinsics { fx: 10.0, fy: 10.0, cx: 0.0, cy: 0.0 };
        // Cell (0, 0) gets the mean of (3, 0) and (1, 0) = (2, 0) -> unit (1, 0); cell (1, 2) gets
        // (0, -4) -> unit (0, -1); a point at the origin feature (0, 0) sits alone in cell (0, 1).
        let points = [[1.0f32, 1.0, 10.0], [2.0, 2.0, 10.0], [9.0, 5.0, 10.0], [5.0, 1.0, 10.0]];
        let features = [3.0f32, 0.0, 1.0, 0.0, 0.0, -4.0, 0.0, 0.0];
        let probs = [0.5f32; 4];
        // Image feature of cell c: channel 0 = c, channel 1 = 10 c.
        let cells = layout.cells();
        let channel_major: Vec<f32> = (0..cells).map(|c| c as f32).chain((0..cells).map(|c| 10.0 * c as f32)).collect();
        let image = ImageGrid::new(&layout, channel_major);
        assert_eq!(&image.cell_major[2..4], &[1.0, 10.0]);
        let mut s2 = vec![f32::NAN; layout.state_2d_len()];
        let mut s3 = vec![f32::NAN; layout.state_3d_len()];
        let score = write_state(&layout, &points, &features, &probs, &image, &k, &Pose::identity(), &mut ScatterScratch::default(), &mut s2, &mut s3);
        assert_eq!(s2.len(), 3 * cells);
        let unit = 2.0 / (2.0 + 1e-6);
        let (row_shift, column_shift, occupancy) = (&s2[..cells], &s2[cells..2 * cells], &s2[2 * cells..]);
        // (0, 0): right neighbour is cell 1 -> 1 * unit; the cell below is cell 3 -> 3 * unit.
        assert!((row_shift[0] - unit).abs() < 1e-6 && (column_shift[0] - 3.0 * unit).abs() < 1e-6, "{s2:?}");
        // (1, 2) = cell 5: no right neighbour, no row below: 0 for both, but occupied.
        assert_eq!((row_shift[5], column_shift[5], occupancy[5]), (0.0, 0.0, 1.0));
        // The zero-feature cell and the empty cells are unoccupied and all zero.
        assert_eq!(occupancy, &[1.0, 0.0, 0.0, 0.0, 0.0, 1.0]);
        assert_eq!(s2.iter().filter(|v| **v != 0.0).count(), 4);
        // The score is the form-independent alignment.
        let features_form = ImageGrid::new(&self::layout(), image.channel_major.clone());
        let mut f2 = vec![0f32; self::layout().state_2d_len()];
        let same = write_state(&self::layout(), &points, &features, &probs, &features_form, &k, &Pose::identity(), &mut ScatterScratch::default(), &mut f2, &mut s3);
        assert_eq!(score, same);
    }

    #[test]
    fn a_near_view_scores_every_pose_within_its_reach_to_the_bit() {
        use nalgebra::{Matrix3, Rotation3, Unit, Vector3};
        use rand::{Rng, SeedableRng};
        let layout = StateLayout { dim: 8, stride: 4, grid_height: 40, grid_width: 128, image_width: 512, image_height: 160, ..layout() };
        let k = Intrinsics { fx: 180.0, fy: 180.0, cx: 249.8, cy: 78.1 };
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        // A scan around the camera, some points within the reach of its centre.
        let points: Vec<[f32; 3]> = (0..30000)
            .map(|i| {
                let (azimuth, range) = (rng.random_range(-3.2f32..3.2), if i % 50 == 0 { rng.random_range(0.2f32..4.0) } else { rng.random_range(2.0f32..60.0) });
                [range * azimuth.cos(), range * azimuth.sin(), rng.random_range(-3.0f32..3.0)]
            })
            .collect();
        let features: Vec<f32> = (0..points.len() * layout.dim).map(|_| rng.random_range(-1.0f32..1.0)).collect();
        let image = ImageGrid::new(&layout, (0..layout.image_feature_len()).map(|_| rng.random_range(-1.0f32..1.0)).collect());
        // Level, looking along map +x, at (1, 2, 0).
        let level = Matrix3::new(0.0, -1.0, 0.0, 0.0, 0.0, -1.0, 1.0, 0.0, 0.0);
        let centre = Pose::from_rt(level, -(level * Vector3::new(1.0, 2.0, 0.0)));
        let (rotation_deg, translation_m) = (20.0, 3.0);
        let near = NearView::new(&layout, &k, &points, &centre, rotation_deg, translation_m);
        assert!(near.len() < points.len() * 2 / 3 && near.len() > points.len() / 10, "kept {}", near.len());
        let narrow = NearView::new(&layout, &k, &points, &centre, 5.0, 0.5);
        let mut scratch = ScatterScratch::default();
        let mut narrow_differs = 0;
        for n in 0..300 {
            // Turned about a random axis and moved in a random direction, every tenth pose by the
            // whole reach.
            let axis = Unit::new_normalize(Vector3::new(rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)));
            let direction = Vector3::new(rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)).normalize();
            let edge = n % 10 == 0;
            let angle = if edge { rotation_deg } else { rng.random_range(0.0..rotation_deg) };
            let shift = if edge { translation_m } else { rng.random_range(0.0..translation_m) };
            let rotation = Rotation3::from_axis_angle(&axis, angle.to_radians()).into_inner() * level;
            let position = Vector3::new(1.0, 2.0, 0.0) + direction * shift;
            let pose = Pose::from_rt(rotation, -(rotation * position));
            let all = alignment(&layout, &points, &features, &image, &k, &pose, &mut scratch);
            assert_eq!(alignment_near(&layout, &near, &features, &image, &k, &pose, &mut scratch).to_bits(), all.to_bits(), "pose {n}");
            narrow_differs += (alignment_near(&layout, &narrow, &features, &image, &k, &pose, &mut scratch) != all) as usize;
        }
        // The test can fail: a view made for a smaller reach misses points these poses see.
        assert!(narrow_differs > 100, "{narrow_differs}");
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
    fn dot_products_agree_to_the_bit() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        for len in (0..20).chain([63, 64, 65, 130]) {
            for _ in 0..50 {
                let mut a: Vec<f32> = (0..len).map(|_| rng.random_range(-1.0f32..1.0) * 10f32.powi(rng.random_range(-6..4))).collect();
                let b: Vec<f32> = (0..len).map(|_| rng.random_range(-1.0f32..1.0)).collect();
                if len > 3 {
                    a[1] = -0.0;
                    a[2] = f32::MIN_POSITIVE / 4.0; // subnormal
                }
                // SAFETY: `Portable` is plain Rust; `Avx` only where the CPU has AVX.
                let portable = unsafe { Portable::dot(&a, &b) };
                let sequential: f64 = a.iter().zip(&b).map(|(x, y)| *x as f64 * *y as f64).sum();
                assert!((portable as f64 - sequential).abs() <= 1e-5 * (1.0 + a.iter().zip(&b).map(|(x, y)| (x * y).abs() as f64).sum::<f64>()));
                #[cfg(target_arch = "x86_64")]
                if std::arch::is_x86_feature_detected!("avx") {
                    assert_eq!(unsafe { Avx::dot(&a, &b) }.to_bits(), portable.to_bits(), "length {len}");
                }
            }
        }
    }

    #[test]
    fn vector_cells_equal_cell_of_for_every_point() {
        // Random points, points on the frustum's edges (cell boundaries, the depth limit, the
        // image border) and non-finite ones, through a turned and shifted pose.
        use rand::{Rng, SeedableRng};
        let layout = StateLayout { grid_height: 40, grid_width: 128, image_width: 512, image_height: 160, ..layout() };
        let k = Intrinsics { fx: 359.4, fy: 341.7, cx: 249.8, cy: 78.1 };
        let pose = Pose::from_rt(
            nalgebra::Rotation3::from_euler_angles(0.02, -0.7, 0.01).into_inner(),
            nalgebra::Vector3::new(0.4, -0.08, 1.3),
        );
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let inverse = pose.inverse();
        let mut points: Vec<[f32; 3]> = (0..20000)
            .map(|_| {
                let p_cam = Point3::new(rng.random_range(-30.0..30.0), rng.random_range(-5.0..5.0), rng.random_range(-2.0..40.0));
                let p = inverse.transform(&p_cam);
                [p.x as f32, p.y as f32, p.z as f32]
            })
            .collect();
        for (u, v, z) in [(-0.5, 10.0, 5.0), (511.5, 10.0, 5.0), (3.5, 3.5, 7.0), (100.0, -0.5, 2.0), (100.0, 159.5, 2.0), (10.0, 10.0, MIN_DEPTH_M)] {
            let p = inverse.transform(&k.back_project(u, v, z));
            points.push([p.x as f32, p.y as f32, p.z as f32]);
        }
        points.extend([[f32::NAN, 0.0, 0.0], [f32::INFINITY, 1.0, 1.0], [0.0, 0.0, f32::NEG_INFINITY]]);
        let rows = matrix_rows(&pose);
        // A power-of-two stride (multiplied by its reciprocal) and another one (divided by).
        for layout in [layout, StateLayout { stride: 3, grid_height: 54, grid_width: 171, ..layout }] {
            let mut cells = vec![0u32; points.len()];
            cells_of(&layout, &k, &rows, &points, &mut cells);
            let mut in_view = 0;
            for (p, c) in points.iter().zip(&cells) {
                let want = layout.cell_of(&k, &transform(&rows, p)).map_or(OUT_OF_VIEW, |c| c as u32);
                assert_eq!(*c, want, "{p:?}, stride {}", layout.stride);
                in_view += (want != OUT_OF_VIEW) as usize;
            }
            assert!(in_view > 1000, "{in_view} points in view: the test would not test much");
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
        let features_form = StateLayout { dim: 64, stride: 4, grid_height: 40, grid_width: 128, image_width: 512, image_height: 160, num_state_points: 2048, xyz_scale_m: 10.0, form: Form2d::Features };
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        let points: Vec<[f32; 3]> = (0..40960).map(|_| [rng.random_range(-40.0..40.0), rng.random_range(-40.0..40.0), rng.random_range(-2.0..3.0)]).collect();
        let features: Vec<f32> = (0..40960 * 64).map(|_| rng.random_range(-0.2..0.2)).collect();
        let probs = vec![0.5f32; 40960];
        let k = Intrinsics { fx: 359.4, fy: 359.4, cx: 249.8, cy: 78.1 };
        let r = nalgebra::Matrix3::new(0.0, -1.0, 0.0, 0.0, 0.0, -1.0, 1.0, 0.0, 0.0);
        let pose = Pose::from_rt(r, nalgebra::Vector3::new(0.0, -0.08, -0.27));
        let correlation = Form2d::Correlation(Shifts::new(&[-24, -16, -10, -6, -3, -1, 0, 1, 3, 6, 10, 16, 24], &[-4, -2, 2, 4]));
        for layout in [features_form, StateLayout { form: correlation, ..features_form }] {
            let image = ImageGrid::new(&layout, (0..layout.image_feature_len()).map(|i| (i % 13) as f32 * 0.01).collect());
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
                "write_state (N = 40960, {} form): {:.3} ms wall, {:.3} ms CPU per state",
                if layout.form == Form2d::Features { "features" } else { "correlation" },
                t.elapsed().as_secs_f64() * 1000.0 / reps as f64,
                (cpu_ms() - c) / reps as f64
            );
        }
    }
}
