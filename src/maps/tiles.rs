//! Regions larger than one scan: the points grouped into ground cells, stored next to the region
//! (`<id>.emb`, magic `CMRTIL01`) and memory-mapped, with (for `CropEmbeddings::Stored` only)
//! point embeddings computed once for the whole region, tile by tile, as float16; a localize
//! takes a virtual LiDAR scan of the points within a radius of its prior camera position, sampled
//! to the model's N ([`TiledMap::around`]), with their stored embeddings or (the server's
//! default, `CropEmbeddings::Encode`, whose file holds none) embeddings the point encoder
//! computes for that crop: the shipped encoder's embeddings depend on where its input's centre
//! is, so the stored ones, computed around each cell's centre, do not serve it (measured in
//! docs/server.md).
//!
//! Why tiles, and what a tile's context is: the point encoder (`training/cmr/models.py`,
//! `PointEncoder`) centres its input on the input's mean and scatters it into a 96 × 0.8 m
//! bird's-eye grid (±38.4 m; farther points are clamped to the border cells) read by a small 2D
//! CNN, so a point's embedding depends on its neighbourhood within a few metres and, through
//! the centring, on where the input's centre is. It was trained on single scans (the sensor near
//! the centre) and is served on N = 40,960 points. So the region is cut into square ground cells
//! of `tile_m`; each cell's points are encoded in passes of N points: up to N/2 of the cell's own
//! points plus the rest drawn from every point within `context_m` of the cell's centre (the disc a
//! request around that place would also crop). Each pass keeps the embeddings of its cell points
//! only, so every point gets exactly one embedding, computed with the context a camera near it
//! would see, and memory stays at one pass (N points) however large the region.
//!
//! Layout (little-endian): magic `CMRTIL01`, 64 ASCII hex model sha, 64 ASCII hex source sha,
//! u64 N, u64 D, u64 point count P, u64 cell count C, f64 tile_m, f64 context_m; C cells of
//! (i32 ix, i32 iy, u64 first point, u64 count) sorted by (ix, iy); P × 3 f32 points (local frame,
//! grouped by cell; within a cell in a seeded random order); P × D f16 embeddings, same order (D = 0: none).
//!
//! A model whose point encoder reads intensity (manifest `points.channels`) needs each cropped
//! point's intensity too: its files (magic `CMRTIL02`) hold P f32 raw intensities (0 where the
//! region has none), same order, between the points and the embeddings; everything else is as in
//! `CMRTIL01`, which every other model's files still are, byte for byte.

use std::collections::HashMap;
use std::io::Write;
use std::path::Path;

use anyhow::{Context, Result, bail};
use half::f16;
use nalgebra::Point3;
use rand::SeedableRng;
use rand::seq::SliceRandom;
use rand::Rng;
use rand_chacha::ChaCha8Rng;

use super::embeddings::fixed_hex;
use super::prepared::centroid;
use super::PreparedMap;
use crate::model::{Backend, Points};

const MAGIC: &[u8; 8] = b"CMRTIL01";
/// `MAGIC` with each point's intensity after the points.
const MAGIC_INTENSITY: &[u8; 8] = b"CMRTIL02";
const HEADER: usize = 8 + 64 + 64 + 8 * 4 + 8 * 2;
const CELL_BYTES: usize = 24;

/// How a large region is tiled and cropped.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TileConfig {
    /// Side of a ground cell, metres.
    pub tile_m: f64,
    /// Radius of the context encoded with a cell, metres (about a request's crop radius).
    pub context_m: f64,
}

impl Default for TileConfig {
    /// 20 m cells with the 40 m context of a default localize crop.
    fn default() -> Self {
        TileConfig { tile_m: 20.0, context_m: 40.0 }
    }
}

/// What building the tiles did.
#[derive(Debug, Clone, Copy, Default)]
pub struct BuildStats {
    pub points: usize,
    pub cells: usize,
    /// Point-encoder calls (each on N points).
    pub passes: usize,
}

#[derive(Debug, Clone, Copy)]
struct Cell {
    ix: i32,
    iy: i32,
    start: usize,
    count: usize,
}

fn cell_of(p: &[f32; 3], tile_m: f64) -> (i32, i32) {
    let c = |v: f32| ((v as f64) / tile_m).floor().clamp(i32::MIN as f64, i32::MAX as f64) as i32;
    (c(p[0]), c(p[1]))
}

/// Indices (into `cells`' point order) of the points within `radius` (ground-plane distance) of
/// `centre`, cell by cell in (ix, iy) order.
fn within(cells: &HashMap<(i32, i32), Cell>, points: impl Fn(usize) -> [f32; 3], tile_m: f64, centre: [f64; 2], radius: f64, out: &mut Vec<u32>) {
    out.clear();
    let lo = |v: f64| ((v - radius) / tile_m).floor() as i64;
    let hi = |v: f64| ((v + radius) / tile_m).floor() as i64;
    let r2 = radius * radius;
    for ix in lo(centre[0])..=hi(centre[0]) {
        for iy in lo(centre[1])..=hi(centre[1]) {
            let (Ok(ix), Ok(iy)) = (i32::try_from(ix), i32::try_from(iy)) else { continue };
            let Some(cell) = cells.get(&(ix, iy)) else { continue };
            for i in cell.start..cell.start + cell.count {
                let p = points(i);
                let (dx, dy) = (p[0] as f64 - centre[0], p[1] as f64 - centre[1]);
                if dx * dx + dy * dy <= r2 {
                    out.push(i as u32);
                }
            }
        }
    }
}

/// The virtual scan's grid: beams (elevation rows), columns (azimuth) and the elevation span,
/// degrees (an HDL-64E-like sensor, the rig the model was trained with).
pub const SCAN_BEAMS: usize = 64;
pub const SCAN_COLUMNS: usize = 2048;
pub const SCAN_ELEVATION_DEG: (f64, f64) = (-25.0, 3.0);

/// Of `candidates`, the nearest to `sensor` in each elevation × azimuth cell, in cell order
/// (row-major: elevation row from [`SCAN_ELEVATION_DEG`]`.0` up, then azimuth column from −180°;
/// the first candidate wins a tie). `training/cmr/data.py::virtual_scan` is its twin, and
/// `fixtures/conventions.json` pins both.
///
/// Work: the candidates are scanned in chunks on rayon's threads, each into a grid of its own,
/// and the grids merged in chunk order keeping the earlier point on equal ranges, which is the
/// sequential scan's answer exactly; a point whose elevation's tangent lies clearly outside the
/// grid's span (by far more than the rounding of the angle computed below) is dropped before
/// its two arc tangents, as the row test would drop it, and most others are binned without
/// them ([`ScanBins`]). The README's fused region: 2.5 M candidates in 186 ms before, about a
/// third of that now (docs/server.md, "Large regions at real-world coordinates").
pub fn virtual_scan(candidates: &[u32], point: impl Fn(u32) -> [f32; 3] + Sync, sensor: [f64; 3]) -> Vec<u32> {
    use rayon::prelude::*;
    const CHUNK: usize = 1 << 18;
    let scan = |chunk: &[u32]| {
        let mut nearest = vec![(f32::INFINITY, u32::MAX); SCAN_BEAMS * SCAN_COLUMNS];
        scan_into(&mut nearest, chunk, &point, sensor);
        nearest
    };
    let nearest = if candidates.len() <= CHUNK {
        scan(candidates)
    } else {
        let grids: Vec<Vec<(f32, u32)>> = candidates.par_chunks(CHUNK).map(scan).collect();
        let mut grids = grids.into_iter();
        let mut nearest = grids.next().expect("at least one chunk");
        for grid in grids {
            for (cell, other) in nearest.iter_mut().zip(grid) {
                if other.0 < cell.0 {
                    *cell = other;
                }
            }
        }
        nearest
    };
    nearest.into_iter().filter(|c| c.1 != u32::MAX).map(|c| c.1).collect()
}

/// [`virtual_scan`]'s sequential scan of `candidates` into `nearest` (range, point) per cell.
fn scan_into(nearest: &mut [(f32, u32)], candidates: &[u32], point: &impl Fn(u32) -> [f32; 3], sensor: [f64; 3]) {
    let (low, high) = SCAN_ELEVATION_DEG;
    // The row test below keeps elevations in [low, high) up to roundings of ~1e-14°; a tangent
    // beyond these by the tables' margin is outside for certain.
    let (tan_low, tan_high) = (low.to_radians().tan() - ScanBins::MARGIN, high.to_radians().tan() + ScanBins::MARGIN);
    let bins = ScanBins::get();
    for &i in candidates {
        let p = point(i);
        let d = [p[0] as f64 - sensor[0], p[1] as f64 - sensor[1], p[2] as f64 - sensor[2]];
        let ground = d[0].hypot(d[1]);
        // Infinite or NaN straight above or below the sensor (ground 0): then the angles decide.
        let tangent = d[2] / ground;
        if ground > 0.0 && !(tan_low..=tan_high).contains(&tangent) {
            continue;
        }
        let (row, column) = match bins.cell(tangent, d[0], d[1]) {
            Some(cell) => cell,
            None => {
                let elevation = d[2].atan2(ground).to_degrees();
                let row = ((elevation - low) / (high - low) * SCAN_BEAMS as f64).floor();
                if !(0.0..SCAN_BEAMS as f64).contains(&row) {
                    continue;
                }
                (row as usize, (((d[1].atan2(d[0]) + std::f64::consts::PI) / std::f64::consts::TAU * SCAN_COLUMNS as f64) as usize).min(SCAN_COLUMNS - 1))
            }
        };
        let range = (ground * ground + d[2] * d[2]).sqrt() as f32;
        let cell = &mut nearest[row * SCAN_COLUMNS + column];
        if range < cell.0 {
            *cell = (range, i);
        }
    }
}

/// The virtual scan's cell of most points without an arc tangent: a row's lower edge as the
/// tangent of its elevation, a column's first edge as the "diamond angle" of its azimuth (a
/// function of x and y alone, increasing with the angle, [`diamond`]), each found from a lookup
/// table and a step or two. Where a point's key lies within [`ScanBins::MARGIN`] of an edge
/// (or outside the grid, or at the azimuth's wrap), [`ScanBins::cell`] gives no answer and the
/// scan computes the angles: the margin is far wider than the roundings of either computation
/// (both keys change by at most as much as the angle in radians), so a cell it gives is the
/// cell the angles give. Checked against the angles in `the_chunked_virtual_scan_keeps_the_sequential_scans_points`.
struct ScanBins {
    /// tan of row r's lower elevation, r = 0..=SCAN_BEAMS.
    row_tan: Vec<f64>,
    /// A row at or below the one of each of [`Self::BUCKETS`] equal slices of `row_tan`'s span.
    row_start: Vec<usize>,
    /// [`diamond`] of column c's first azimuth + π (the scan's angle), c = 0..=SCAN_COLUMNS.
    column_key: Vec<f64>,
    /// A column at or below the one of each of [`Self::BUCKETS`] equal slices of 0..4.
    column_start: Vec<usize>,
}

impl ScanBins {
    const MARGIN: f64 = 1e-9;
    const BUCKETS: usize = 8192;

    fn get() -> &'static ScanBins {
        static BINS: std::sync::OnceLock<ScanBins> = std::sync::OnceLock::new();
        BINS.get_or_init(|| {
            let (low, high) = SCAN_ELEVATION_DEG;
            let row_tan: Vec<f64> = (0..=SCAN_BEAMS).map(|r| (low + (high - low) * r as f64 / SCAN_BEAMS as f64).to_radians().tan()).collect();
            let column_key: Vec<f64> = (0..=SCAN_COLUMNS)
                .map(|c| match c {
                    0 => 0.0,
                    SCAN_COLUMNS => 4.0,
                    _ => {
                        let angle = std::f64::consts::TAU * c as f64 / SCAN_COLUMNS as f64;
                        diamond(angle.cos(), angle.sin())
                    }
                })
                .collect();
            let starts = |edges: &[f64], from: f64, to: f64| -> Vec<usize> {
                (0..Self::BUCKETS).map(|b| edges.iter().rposition(|&e| e <= from + (to - from) * b as f64 / Self::BUCKETS as f64).unwrap_or(0).min(edges.len() - 2)).collect()
            };
            let row_start = starts(&row_tan, row_tan[0], row_tan[SCAN_BEAMS]);
            let column_start = starts(&column_key, 0.0, 4.0);
            ScanBins { row_tan, row_start, column_key, column_start }
        })
    }

    /// (row, column) of the offset (`x`, `y`) from the sensor whose elevation's tangent is
    /// `tangent` (height over ground distance; not finite at ground distance 0, which gives
    /// `None`), or `None` where only the angles can tell.
    #[inline]
    fn cell(&self, tangent: f64, x: f64, y: f64) -> Option<(usize, usize)> {
        let row = Self::find(&self.row_tan, &self.row_start, tangent)?;
        // The scan's azimuth is atan2(y, x) + π: the direction (−x, −y)'s angle.
        let column = Self::find(&self.column_key, &self.column_start, diamond(-x, -y))?;
        Some((row, column))
    }

    /// The slice k of `edges` with edges[k] + MARGIN <= key < edges[k + 1] − MARGIN.
    #[inline]
    fn find(edges: &[f64], start: &[usize], key: f64) -> Option<usize> {
        let (first, last) = (edges[0], edges[edges.len() - 1]);
        if !(key >= first + Self::MARGIN && key < last - Self::MARGIN) {
            return None;
        }
        let bucket = (((key - first) / (last - first) * Self::BUCKETS as f64) as usize).min(Self::BUCKETS - 1);
        let mut k = start[bucket];
        while key >= edges[k + 1] {
            k += 1;
        }
        while key < edges[k] {
            k -= 1;
        }
        (key - edges[k] >= Self::MARGIN && edges[k + 1] - key >= Self::MARGIN).then_some(k)
    }
}

/// The "diamond angle" of the direction (x, y): 0..4 once round, increasing with the direction's
/// angle from +x towards +y (0 at +x, 1 at +y, 2 at −x, 3 at −y), changing by at most the angle's
/// change in radians. No arc tangent: one division.
#[inline]
fn diamond(x: f64, y: f64) -> f64 {
    if y >= 0.0 {
        if x >= 0.0 { y / (x + y) } else { 1.0 - x / (y - x) }
    } else if x < 0.0 {
        2.0 - y / (-x - y)
    } else {
        3.0 + x / (x - y)
    }
}

/// `n` of `candidates` (ChaCha8 with `seed`): distinct ones when there are enough, else every one
/// and the rest drawn with replacement (as [`super::sample_points`] fills a small cloud).
fn sample_indices(candidates: &[u32], n: usize, seed: u64) -> Vec<u32> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    if candidates.len() >= n {
        return rand::seq::index::sample(&mut rng, candidates.len(), n).into_iter().map(|k| candidates[k]).collect();
    }
    let mut out = candidates.to_vec();
    out.shuffle(&mut rng);
    while out.len() < n && !candidates.is_empty() {
        out.push(candidates[rng.random_range(0..candidates.len())]);
    }
    out
}

/// Groups a region (`cloud` in its local frame) into tiles and writes the `CMRTIL01` file to
/// `out` (`CMRTIL02`, with each point's intensity, for a model that reads it); with
/// `embeddings`, each tile's points are encoded too (D = the model's feature size), else the
/// file holds the cell table and the points only (D = 0: what a server that encodes every crop
/// itself, `CropEmbeddings::Encode`, reads, without a point-encoder pass over the whole region).
/// Memory: the points twice (as given and grouped by cell), a cell's context indices and one
/// encoder pass. Errors: an intensity that is not one value per point, the encoder's, or the
/// writer's.
pub fn build(backend: &mut dyn Backend, cloud: Points<'_>, config: TileConfig, embeddings: bool, model_sha: &str, source_sha: &str, out: &mut dyn Write) -> Result<BuildStats> {
    cloud.check()?;
    let points = cloud.xyz;
    let n = backend.manifest().points.num_points;
    let d = if embeddings { backend.manifest().features.dim } else { 0 };
    let with_intensity = backend.manifest().reads_intensity();
    if points.is_empty() {
        bail!("the region has no points");
    }
    if points.len() > u32::MAX as usize {
        bail!("a region holds at most {} points", u32::MAX);
    }
    // A seeded shuffle, then a stable sort by cell: each cell's points in random order, so any
    // prefix of a cell is a fair sample of it.
    let mut order: Vec<u32> = (0..points.len() as u32).collect();
    order.shuffle(&mut ChaCha8Rng::seed_from_u64(1));
    order.sort_by_key(|&i| cell_of(&points[i as usize], config.tile_m));
    let sorted: Vec<[f32; 3]> = order.iter().map(|&i| points[i as usize]).collect();
    let sorted_intensity: Option<Vec<f32>> = with_intensity.then(|| match cloud.intensity {
        Some(values) => order.iter().map(|&i| values[i as usize]).collect(),
        None => vec![0.0; sorted.len()],
    });
    drop(order);
    let mut cells: Vec<Cell> = Vec::new();
    for (i, p) in sorted.iter().enumerate() {
        let (ix, iy) = cell_of(p, config.tile_m);
        match cells.last_mut() {
            Some(c) if (c.ix, c.iy) == (ix, iy) => c.count += 1,
            _ => cells.push(Cell { ix, iy, start: i, count: 1 }),
        }
    }
    let lookup: HashMap<(i32, i32), Cell> = cells.iter().map(|c| ((c.ix, c.iy), *c)).collect();

    out.write_all(if with_intensity { MAGIC_INTENSITY } else { MAGIC })?;
    out.write_all(&fixed_hex(model_sha))?;
    out.write_all(&fixed_hex(source_sha))?;
    for v in [n as u64, d as u64, sorted.len() as u64, cells.len() as u64] {
        out.write_all(&v.to_le_bytes())?;
    }
    out.write_all(&config.tile_m.to_le_bytes())?;
    out.write_all(&config.context_m.to_le_bytes())?;
    for c in &cells {
        out.write_all(&c.ix.to_le_bytes())?;
        out.write_all(&c.iy.to_le_bytes())?;
        out.write_all(&(c.start as u64).to_le_bytes())?;
        out.write_all(&(c.count as u64).to_le_bytes())?;
    }
    for p in &sorted {
        for v in p {
            out.write_all(&v.to_le_bytes())?;
        }
    }
    for v in sorted_intensity.iter().flatten() {
        out.write_all(&v.to_le_bytes())?;
    }

    let mut stats = BuildStats { points: sorted.len(), cells: cells.len(), passes: 0 };
    if !embeddings {
        out.flush()?;
        return Ok(stats);
    }
    let core_max = (n / 2).max(1);
    let mut context = Vec::new();
    let mut chosen: Vec<usize> = Vec::with_capacity(n);
    let mut input: Vec<[f32; 3]> = Vec::with_capacity(n);
    let mut input_intensity: Vec<f32> = Vec::with_capacity(if with_intensity { n } else { 0 });
    let mut row = vec![0u8; core_max * d * 2];
    for (k, cell) in cells.iter().enumerate() {
        let centre = [(cell.ix as f64 + 0.5) * config.tile_m, (cell.iy as f64 + 0.5) * config.tile_m];
        within(&lookup, |i| sorted[i], config.tile_m, centre, config.context_m, &mut context);
        let mut first = cell.start;
        while first < cell.start + cell.count {
            let last = (first + core_max).min(cell.start + cell.count);
            let others: Vec<u32> = context.iter().copied().filter(|&i| !(first..last).contains(&(i as usize))).collect();
            chosen.clear();
            chosen.extend(first..last);
            let fill = sample_indices(if others.is_empty() { &[] } else { &others }, n - chosen.len(), (k as u64) << 32 | first as u64);
            chosen.extend(fill.iter().map(|&i| i as usize));
            while chosen.len() < n {
                chosen.push(chosen[chosen.len() % (last - first)]);
            }
            input.clear();
            input.extend(chosen.iter().map(|&i| sorted[i]));
            let intensity = sorted_intensity.as_ref().map(|values| {
                input_intensity.clear();
                input_intensity.extend(chosen.iter().map(|&i| values[i]));
                &input_intensity[..]
            });
            let features = backend.encode_points(Points::new(&input, intensity)).with_context(|| format!("point encoder on cell ({}, {})", cell.ix, cell.iy))?;
            stats.passes += 1;
            let keep = (last - first) * d;
            for (o, v) in row.chunks_exact_mut(2).zip(&features[..keep]) {
                o.copy_from_slice(&f16::from_f32(*v).to_le_bytes());
            }
            out.write_all(&row[..keep * 2])?;
            first = last;
        }
    }
    out.flush()?;
    Ok(stats)
}

/// A tiled region's `<id>.emb`, memory-mapped: the cell table in memory, points and embeddings
/// read from the mapping when a request crops them.
pub struct TiledMap {
    map: memmap2::Mmap,
    cells: HashMap<(i32, i32), Cell>,
    pub n: usize,
    /// Features per stored embedding; 0 when the file holds no embeddings ([`build`] without).
    pub d: usize,
    pub points: usize,
    pub config: TileConfig,
    points_at: usize,
    /// Where each point's f32 intensity starts (a `CMRTIL02` file), `None` without.
    intensity_at: Option<usize>,
    features_at: usize,
}

/// Why a crop could not be made.
#[derive(Debug, Clone, thiserror::Error)]
#[error("only {found} map points lie within {radius_m} m of the prior camera position ({x:.1}, {y:.1}) in the region's local frame; at least {needed} are needed (a larger radius_m, or a prior inside the mapped area)")]
pub struct SparseCrop {
    pub found: usize,
    pub needed: usize,
    pub radius_m: f64,
    pub x: f64,
    pub y: f64,
}

impl TiledMap {
    /// Opens and checks a tiled `<id>.emb`: `Ok(None)` when it is another model's or another
    /// cloud's, or a whole-region file; `Err` when it cannot be read or is damaged.
    pub fn open(path: &Path, model_sha: &str, source_sha: &str) -> Result<Option<TiledMap>> {
        let file = std::fs::File::open(path).with_context(|| format!("opening {}", path.display()))?;
        // SAFETY: the store replaces `<id>.emb` only by renaming a new file over it, never by
        // writing into it, so the mapped file does not change under us.
        let map = unsafe { memmap2::Mmap::map(&file) }.with_context(|| format!("mapping {}", path.display()))?;
        if map.len() < HEADER || !is_tiled(&map) || map[8..72] != fixed_hex(model_sha) || map[72..136] != fixed_hex(source_sha) {
            return Ok(None);
        }
        let u = |at: usize| u64::from_le_bytes(map[at..at + 8].try_into().unwrap()) as usize;
        let f = |at: usize| f64::from_le_bytes(map[at..at + 8].try_into().unwrap());
        let (n, d, points, count) = (u(136), u(144), u(152), u(160));
        let config = TileConfig { tile_m: f(168), context_m: f(176) };
        let points_at = count.checked_mul(CELL_BYTES).and_then(|c| c.checked_add(HEADER)).context("cell table overflows")?;
        let with_intensity = &map[..8] == MAGIC_INTENSITY;
        let point_bytes = if with_intensity { 16 } else { 12 };
        let features_at = points.checked_mul(point_bytes).and_then(|p| p.checked_add(points_at)).context("points overflow")?;
        let intensity_at = with_intensity.then(|| points_at + points * 12);
        let end = points.checked_mul(d * 2).and_then(|f| f.checked_add(features_at)).context("features overflow")?;
        if end != map.len() || !(config.tile_m > 0.0) {
            bail!("{}: {} bytes, the header says {end}", path.display(), map.len());
        }
        let mut cells = HashMap::with_capacity(count);
        let mut next = 0;
        for k in 0..count {
            let at = HEADER + k * CELL_BYTES;
            let ix = i32::from_le_bytes(map[at..at + 4].try_into().unwrap());
            let iy = i32::from_le_bytes(map[at + 4..at + 8].try_into().unwrap());
            let (start, count) = (u(at + 8), u(at + 16));
            if start != next || count == 0 {
                bail!("{}: cell {k} is out of order", path.display());
            }
            next = start + count;
            cells.insert((ix, iy), Cell { ix, iy, start, count });
        }
        if next != points {
            bail!("{}: the cells hold {next} of {points} points", path.display());
        }
        #[cfg(unix)]
        let _ = map.advise(memmap2::Advice::Random);
        Ok(Some(TiledMap { map, cells, n, d, points, config, points_at, intensity_at, features_at }))
    }

    fn point(&self, i: usize) -> [f32; 3] {
        let at = self.points_at + i * 12;
        let f = |k: usize| f32::from_le_bytes(self.map[at + 4 * k..at + 4 * k + 4].try_into().unwrap());
        [f(0), f(1), f(2)]
    }

    fn intensity(&self, i: usize) -> Option<f32> {
        let at = self.intensity_at? + i * 4;
        Some(f32::from_le_bytes(self.map[at..at + 4].try_into().unwrap()))
    }

    /// Whether the file holds each point's intensity (`CMRTIL02`: a model that reads it).
    pub fn has_intensity(&self) -> bool {
        self.intensity_at.is_some()
    }

    pub fn cells(&self) -> usize {
        self.cells.len()
    }

    /// Up to `max` stored points (local frame) spread over the whole region: every k-th point of
    /// the file, k = ceil(points / max). For drawing the region.
    pub fn spread(&self, max: usize) -> Vec<[f32; 3]> {
        let step = self.points.div_ceil(max.max(1)).max(1);
        (0..self.points).step_by(step).map(|i| self.point(i)).collect()
    }

    /// Bytes of the mapped file.
    pub fn file_bytes(&self) -> usize {
        self.map.len()
    }

    /// Heap memory held (the cell table), for the cache's byte budget.
    pub fn heap_bytes(&self) -> usize {
        self.cells.capacity() * (CELL_BYTES + 16) + std::mem::size_of::<Self>()
    }

    /// A virtual LiDAR scan of the region from `sensor` (local frame, metres; the prior camera's
    /// position): of the points within `radius_m` (ground-plane distance), the nearest one in
    /// each cell of a [`SCAN_BEAMS`] × [`SCAN_COLUMNS`] elevation × azimuth grid (elevations
    /// [`SCAN_ELEVATION_DEG`]), so the crop has a scan's occlusion and its density falling with
    /// range, what the point encoder was trained on; then the model's N of them, drawn by
    /// ChaCha8(seed 0), with their stored embeddings: a prepared map like a whole region's, pivot
    /// at its centroid. Without `stored_features` the features are left empty (the caller
    /// encodes the crop), and no page of the embeddings is touched.
    /// Errors: fewer than `min_points` points in the virtual scan.
    pub fn around(&self, sensor: [f64; 3], radius_m: f64, min_points: usize, stored_features: bool) -> Result<PreparedMap, SparseCrop> {
        let mut candidates = Vec::new();
        within(&self.cells, |i| self.point(i), self.config.tile_m, [sensor[0], sensor[1]], radius_m, &mut candidates);
        let visible = virtual_scan(&candidates, |i| self.point(i as usize), sensor);
        if visible.len() < min_points.max(1) {
            return Err(SparseCrop { found: visible.len(), needed: min_points.max(1), radius_m, x: sensor[0], y: sensor[1] });
        }
        let chosen = sample_indices(&visible, self.n, 0);
        let points: Vec<[f32; 3]> = chosen.iter().map(|&i| self.point(i as usize)).collect();
        let mut features = Vec::with_capacity(if stored_features { chosen.len() * self.d } else { 0 });
        for &i in chosen.iter().filter(|_| stored_features) {
            let at = self.features_at + i as usize * self.d * 2;
            features.extend(self.map[at..at + self.d * 2].chunks_exact(2).map(|b| f16::from_le_bytes([b[0], b[1]]).to_f32()));
        }
        let intensity: Option<Vec<f32>> = self.has_intensity().then(|| chosen.iter().filter_map(|&i| self.intensity(i as usize)).collect());
        let pivot: Point3<f64> = centroid(&points);
        Ok(PreparedMap { points, features, pivot, source_points: candidates.len(), intensity })
    }
}

/// Whether `bytes` (the start of an `<id>.emb`) is a tiled file (with or without intensity).
pub fn is_tiled(bytes: &[u8]) -> bool {
    bytes.starts_with(MAGIC) || bytes.starts_with(MAGIC_INTENSITY)
}

/// The cell count in a tiled file's header, when `bytes` holds it.
pub fn header_cells(bytes: &[u8]) -> Option<usize> {
    (is_tiled(bytes) && bytes.len() >= HEADER).then(|| u64::from_le_bytes(bytes[160..168].try_into().unwrap()) as usize)
}

pub const HEADER_BYTES: usize = HEADER;

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::{FakeBackend, Manifest};

    /// The chunked scan with its tangent pre-test and its tables ([`ScanBins`]) keeps exactly the
    /// points of the plain sequential scan (the oracle below, the function as it was): a cloud of
    /// more than one chunk, with points on and just beside the elevation span's edges and every
    /// column's edge, and duplicates whose tie the first must win.
    #[test]
    fn the_chunked_virtual_scan_keeps_the_sequential_scans_points() {
        fn oracle(candidates: &[u32], point: impl Fn(u32) -> [f32; 3], sensor: [f64; 3]) -> Vec<u32> {
            let mut nearest = vec![(f32::INFINITY, u32::MAX); SCAN_BEAMS * SCAN_COLUMNS];
            let (low, high) = SCAN_ELEVATION_DEG;
            for &i in candidates {
                let p = point(i);
                let d = [p[0] as f64 - sensor[0], p[1] as f64 - sensor[1], p[2] as f64 - sensor[2]];
                let ground = d[0].hypot(d[1]);
                let elevation = d[2].atan2(ground).to_degrees();
                let row = ((elevation - low) / (high - low) * SCAN_BEAMS as f64).floor();
                if !(0.0..SCAN_BEAMS as f64).contains(&row) {
                    continue;
                }
                let column = (((d[1].atan2(d[0]) + std::f64::consts::PI) / std::f64::consts::TAU * SCAN_COLUMNS as f64) as usize).min(SCAN_COLUMNS - 1);
                let range = (ground * ground + d[2] * d[2]).sqrt() as f32;
                let cell = &mut nearest[row as usize * SCAN_COLUMNS + column];
                if range < cell.0 {
                    *cell = (range, i);
                }
            }
            nearest.into_iter().filter(|c| c.1 != u32::MAX).map(|c| c.1).collect()
        }
        let sensor = [1.5, -2.0, 1.73];
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let mut points: Vec<[f32; 3]> = (0..700_000)
            .map(|_| [rng.random_range(-60.0..60.0f32), rng.random_range(-60.0..60.0f32), rng.random_range(-3.0..12.0f32)])
            .collect();
        // On the span's edges and a hair inside or outside them, at several distances and bearings.
        for k in 0..2000 {
            let (ground, bearing) = (1.0 + k as f64 * 0.03, k as f64 * 0.7);
            for deg in [-25.0f64, 3.0] {
                for nudge in [-1e-7, 0.0, 1e-7] {
                    let z = sensor[2] + ground * (deg + nudge).to_radians().tan();
                    points.push([(sensor[0] + ground * bearing.cos()) as f32, (sensor[1] + ground * bearing.sin()) as f32, z as f32]);
                }
            }
        }
        // On and beside every column's edge (the azimuth), and on the quadrants' axes.
        for c in 0..SCAN_COLUMNS {
            let edge = -std::f64::consts::PI + std::f64::consts::TAU * c as f64 / SCAN_COLUMNS as f64;
            for nudge in [-1e-10, 0.0, 1e-10] {
                let (ground, bearing) = (5.0 + (c % 40) as f64, edge + nudge);
                points.push([(sensor[0] + ground * bearing.cos()) as f32, (sensor[1] + ground * bearing.sin()) as f32, (sensor[2] - 0.5) as f32]);
            }
        }
        for (x, y) in [(7.0, 0.0), (-7.0, 0.0), (0.0, 7.0), (0.0, -7.0)] {
            points.push([(sensor[0] + x) as f32, (sensor[1] + y) as f32, (sensor[2] - 0.5) as f32]);
        }
        // Duplicates far apart in the candidate order (different chunks): equal ranges.
        for k in 0..1000 {
            points.push(points[k * 7]);
        }
        let candidates: Vec<u32> = (0..points.len() as u32).collect();
        assert!(candidates.len() > 2 << 18, "more than two chunks");
        // The tables bin nearly every point in the span without the angles.
        let (bins, (low, high)) = (ScanBins::get(), SCAN_ELEVATION_DEG);
        let (mut in_span, mut binned) = (0, 0);
        for p in &points[..100_000] {
            let d = [p[0] as f64 - sensor[0], p[1] as f64 - sensor[1], p[2] as f64 - sensor[2]];
            let ground = d[0].hypot(d[1]);
            let elevation = d[2].atan2(ground).to_degrees();
            if elevation > low + 0.01 && elevation < high - 0.01 {
                in_span += 1;
                binned += bins.cell(d[2] / ground, d[0], d[1]).is_some() as usize;
            }
        }
        assert!(in_span > 20_000 && binned as f64 > 0.999 * in_span as f64, "{binned} of {in_span}");
        let kept = virtual_scan(&candidates, |i| points[i as usize], sensor);
        assert_eq!(kept, oracle(&candidates, |i| points[i as usize], sensor));
        assert!(kept.len() > 50_000, "{}", kept.len());
        // Shuffled, so ties and chunks fall elsewhere.
        let mut shuffled = candidates.clone();
        shuffled.shuffle(&mut rng);
        assert_eq!(virtual_scan(&shuffled, |i| points[i as usize], sensor), oracle(&shuffled, |i| points[i as usize], sensor));
    }

    #[test]
    fn every_point_gets_one_embedding_and_crops_read_them_back() {
        let mut manifest = Manifest::load(&std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/tiny-model")).unwrap();
        manifest.points.num_points = 64;
        manifest.points.num_state_points = 8;
        let mut backend = FakeBackend::new(std::sync::Arc::new(manifest));
        // 3 × 2 cells of 10 m, 150 points each.
        let points: Vec<[f32; 3]> = (0..900).map(|i| [(i % 30) as f32 + 0.5, ((i / 30) % 20) as f32 + 0.25, (i % 7) as f32 * 0.1]).collect();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("r.emb");
        let mut file = std::io::BufWriter::new(std::fs::File::create(&path).unwrap());
        let config = TileConfig { tile_m: 10.0, context_m: 12.0 };
        let stats = build(&mut backend, Points::xyz(&points), config, true, "aa", "bb", &mut file).unwrap();
        drop(file);
        assert_eq!((stats.points, stats.cells), (900, 6));
        assert!(stats.passes >= 6);
        assert!(TiledMap::open(&path, "other", "bb").unwrap().is_none());
        let tiled = TiledMap::open(&path, "aa", "bb").unwrap().unwrap();
        assert_eq!((tiled.points, tiled.cells(), tiled.n), (900, 6, 64));
        // Every stored point is one of the region's, once.
        let mut stored: Vec<[u32; 3]> = (0..900).map(|i| tiled.point(i).map(f32::to_bits)).collect();
        let mut given: Vec<[u32; 3]> = points.iter().map(|p| p.map(f32::to_bits)).collect();
        stored.sort();
        given.sort();
        assert_eq!(stored, given);
        // The fake encoder's features depend on the point only: the stored f16 ones match.
        let crop = tiled.around([15.0, 10.0, 1.0], 6.0, 10, true).unwrap();
        assert_eq!(crop.points.len(), 64);
        let direct = backend.encode_points(crop.input()).unwrap();
        let worst = direct.iter().zip(&crop.features).map(|(a, b)| (a - b).abs()).fold(0f32, f32::max);
        assert!(worst < 2e-3, "f16 round trip {worst}");
        assert!(crop.points.iter().all(|p| (p[0] as f64 - 15.0).hypot(p[1] as f64 - 10.0) <= 6.0));
        assert_eq!(tiled.around([15.0, 10.0, 1.0], 6.0, 10, false).unwrap().points, crop.points, "deterministic");
        let sparse = tiled.around([500.0, 500.0, 1.0], 40.0, 10, true).unwrap_err();
        assert_eq!(sparse.found, 0);

        // Without embeddings: no encoder pass, the cell table and points alone (D = 0), and the
        // same crops to the bit.
        let bare = dir.path().join("bare.emb");
        let mut file = std::io::BufWriter::new(std::fs::File::create(&bare).unwrap());
        let stats = build(&mut backend, Points::xyz(&points), config, false, "aa", "bb", &mut file).unwrap();
        drop(file);
        assert_eq!((stats.points, stats.cells, stats.passes), (900, 6, 0));
        let points_only = TiledMap::open(&bare, "aa", "bb").unwrap().unwrap();
        assert_eq!((points_only.d, points_only.points, points_only.cells(), points_only.n), (0, 900, 6, 64));
        assert_eq!(points_only.file_bytes(), HEADER + 6 * CELL_BYTES + 900 * 12);
        assert_eq!(points_only.file_bytes() + 900 * tiled.d * 2, tiled.file_bytes());
        for sensor in [[15.0, 10.0, 1.0], [3.0, 4.0, 0.5], [28.0, 18.0, 2.0]] {
            let (a, b) = (points_only.around(sensor, 9.0, 10, false).unwrap(), tiled.around(sensor, 9.0, 10, false).unwrap());
            assert_eq!((a.points, a.source_points), (b.points, b.source_points));
        }
    }

    /// A model that reads intensity: its file (`CMRTIL02`) holds each point's intensity, a crop
    /// carries that of each of its points, and the encoder reads it (the fake's features move
    /// with the rank); the cells, points and crops are those of a file without it. A region
    /// without intensity stores zeros (a constant: rank 0.5).
    #[test]
    fn a_model_that_reads_intensity_keeps_it_in_the_tiles_and_its_crops() {
        let mut manifest = Manifest::load(&std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/tiny-model")).unwrap();
        manifest.points.num_points = 64;
        manifest.points.num_state_points = 8;
        let plain_manifest = manifest.clone();
        manifest.points.channels = Some(crate::model::POINT_CHANNELS_INTENSITY.map(String::from).to_vec());
        let mut backend = FakeBackend::new(std::sync::Arc::new(manifest));
        let points: Vec<[f32; 3]> = (0..900).map(|i| [(i % 30) as f32 + 0.5, ((i / 30) % 20) as f32 + 0.25, (i % 7) as f32 * 0.1]).collect();
        let intensity: Vec<f32> = (0..900).map(|i| ((i * 37) % 101) as f32 / 100.0).collect();
        let of: HashMap<[u32; 3], f32> = points.iter().zip(&intensity).map(|(p, &v)| (p.map(f32::to_bits), v)).collect();
        assert_eq!(of.len(), 900, "distinct points");
        let dir = tempfile::tempdir().unwrap();
        let config = TileConfig { tile_m: 10.0, context_m: 12.0 };
        let write = |backend: &mut FakeBackend, name: &str, cloud: Points<'_>, embeddings: bool| {
            let path = dir.path().join(name);
            let mut file = std::io::BufWriter::new(std::fs::File::create(&path).unwrap());
            build(backend, cloud, config, embeddings, "aa", "bb", &mut file).unwrap();
            drop(file);
            path
        };
        let path = write(&mut backend, "i.emb", Points::new(&points, Some(&intensity)), true);
        assert_eq!(&std::fs::read(&path).unwrap()[..8], MAGIC_INTENSITY);
        let tiled = TiledMap::open(&path, "aa", "bb").unwrap().unwrap();
        assert!(tiled.has_intensity());
        assert_eq!(tiled.file_bytes(), HEADER + 6 * CELL_BYTES + 900 * 16 + 900 * tiled.d * 2);
        let crop = tiled.around([15.0, 10.0, 1.0], 6.0, 10, true).unwrap();
        let kept = crop.intensity.clone().expect("the crop's intensity");
        assert_eq!(kept, crop.points.iter().map(|p| of[&p.map(f32::to_bits)]).collect::<Vec<_>>());
        let with = backend.encode_points(crop.input()).unwrap();
        let without = backend.encode_points(Points::xyz(&crop.points)).unwrap();
        let moved = with.iter().zip(&without).map(|(a, b)| (a - b).abs()).fold(0f32, f32::max);
        assert!(moved > 0.1, "the features follow the intensity: {moved}");

        // The same cells, points and crops as a three-column model's file (`CMRTIL01`).
        let mut plain = FakeBackend::new(std::sync::Arc::new(plain_manifest));
        let plain_path = write(&mut plain, "p.emb", Points::new(&points, Some(&intensity)), false);
        let bytes = std::fs::read(&plain_path).unwrap();
        assert_eq!(&bytes[..8], MAGIC);
        let bare = write(&mut plain, "q.emb", Points::xyz(&points), false);
        assert_eq!(bytes, std::fs::read(&bare).unwrap(), "a three-column file does not depend on the intensity");
        let plain = TiledMap::open(&plain_path, "aa", "bb").unwrap().unwrap();
        assert!(!plain.has_intensity());
        let a = plain.around([15.0, 10.0, 1.0], 6.0, 10, false).unwrap();
        assert_eq!((a.points, a.intensity), (crop.points.clone(), None));

        // A region without intensity, for a model that reads it: zeros, read as a constant.
        let zeros = write(&mut backend, "z.emb", Points::xyz(&points), false);
        let zeros = TiledMap::open(&zeros, "aa", "bb").unwrap().unwrap();
        let crop = zeros.around([15.0, 10.0, 1.0], 6.0, 10, false).unwrap();
        assert!(crop.intensity.as_ref().unwrap().iter().all(|&v| v == 0.0));
        assert_eq!(backend.encode_points(crop.input()).unwrap(), without);
    }
}
