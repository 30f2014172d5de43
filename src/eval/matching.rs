//! 2D–3D matching for the one-shot baseline: mutual nearest neighbours between point
//! embeddings and image-feature cells, by cosine similarity (both are L2-normalised, so a dot
//! product), computed as blocked matrix products so memory stays bounded for 40,960 points.

use ndarray::{Array2, ArrayView2};

/// A point and an image cell that are each other's most similar partner.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FeatureMatch {
    /// Index into the map's N sampled points.
    pub point: usize,
    /// Cell index row * grid_width + col in the feature grid.
    pub cell: usize,
    pub similarity: f32,
}

/// Rows of the point-feature matrix multiplied at once: 1024 × 5120 cells × 4 B = 21 MB per
/// block; blocks run in parallel (rayon).
const BLOCK: usize = 1024;

/// How point–cell pairs are chosen.
#[derive(Debug, Clone, Copy, PartialEq, clap::ValueEnum, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum MatchStrategy {
    /// Keep a pair only when each is the other's most similar partner.
    Mutual,
    /// Each point's most similar cell, kept when Lowe's ratio of feature distances
    /// (best / second best, distance = sqrt(2 − 2·cos)) is below `RATIO`, where the second best
    /// is taken outside the best cell's (2·`RATIO_EXCLUSION_CELLS` + 1)² neighbourhood (image
    /// features vary smoothly, so a neighbour of the right cell is no rival); the most similar
    /// `MAX_RATIO_MATCHES` pairs are kept.
    Ratio,
}

pub const RATIO: f32 = 0.9;
pub const MAX_RATIO_MATCHES: usize = 4000;
pub const RATIO_EXCLUSION_CELLS: usize = 2;

/// Per candidate point: best cell and similarity, and the best similarity outside the best
/// cell's neighbourhood.
struct PointBest {
    cell: usize,
    best: f32,
    second: f32,
}

/// Scores every candidate against every cell: per point its best two cells, per cell its best
/// point (as an index into `candidates`).
/// Per candidate its best cells, and per cell its best candidate (index, similarity).
type Scores = (Vec<PointBest>, Vec<(usize, f32)>);

fn score(point_features: &[f32], dim: usize, candidates: &[usize], image: ArrayView2<f32>, grid_width: usize) -> Scores {
    use rayon::prelude::*;
    let cells = image.ncols();
    let blocks: Vec<Scores> = candidates
        .par_chunks(BLOCK)
        .enumerate()
        .map(|(block_index, block)| {
            let mut rows = Array2::<f32>::zeros((block.len(), dim));
            for (r, &p) in block.iter().enumerate() {
                rows.row_mut(r).assign(&ndarray::ArrayView1::from(&point_features[p * dim..(p + 1) * dim]));
            }
            let similarity = rows.dot(&image);
            let mut cell_best = vec![(usize::MAX, f32::NEG_INFINITY); cells];
            let mut point_best = Vec::with_capacity(block.len());
            for (r, row) in similarity.outer_iter().enumerate() {
                let candidate = block_index * BLOCK + r;
                let mut pb = PointBest { cell: 0, best: f32::NEG_INFINITY, second: f32::NEG_INFINITY };
                for (c, &s) in row.iter().enumerate() {
                    if s > pb.best {
                        pb.cell = c;
                        pb.best = s;
                    }
                    if s > cell_best[c].1 {
                        cell_best[c] = (candidate, s);
                    }
                }
                let (best_row, best_col) = (pb.cell / grid_width, pb.cell % grid_width);
                for (c, &s) in row.iter().enumerate() {
                    let near = (c / grid_width).abs_diff(best_row) <= RATIO_EXCLUSION_CELLS && (c % grid_width).abs_diff(best_col) <= RATIO_EXCLUSION_CELLS;
                    if !near && s > pb.second {
                        pb.second = s;
                    }
                }
                point_best.push(pb);
            }
            (point_best, cell_best)
        })
        .collect();
    let mut best_cell_of_point = Vec::with_capacity(candidates.len());
    let mut best_point_of_cell = vec![(usize::MAX, f32::NEG_INFINITY); cells];
    for (points, cell_best) in blocks {
        best_cell_of_point.extend(points);
        for (c, (candidate, s)) in cell_best.into_iter().enumerate() {
            if s > best_point_of_cell[c].1 {
                best_point_of_cell[c] = (candidate, s);
            }
        }
    }
    (best_cell_of_point, best_point_of_cell)
}

/// Mutual nearest neighbours between `candidates` (indices of rows of `point_features`,
/// [N, dim] row-major) and the cells of `image_features` ([dim, cells] channel-major).
pub fn mutual_nearest(point_features: &[f32], dim: usize, candidates: &[usize], image_features: &[f32]) -> Vec<FeatureMatch> {
    let cells = image_features.len().checked_div(dim).unwrap_or(0);
    find_matches(point_features, dim, candidates, image_features, cells.max(1), MatchStrategy::Mutual)
}

/// Point–cell matches by `strategy` (see [`MatchStrategy`]); cells are `grid_width` per row.
pub fn find_matches(
    point_features: &[f32],
    dim: usize,
    candidates: &[usize],
    image_features: &[f32],
    grid_width: usize,
    strategy: MatchStrategy,
) -> Vec<FeatureMatch> {
    if dim == 0 || grid_width == 0 || candidates.is_empty() || image_features.len() % dim != 0 || point_features.len() < dim * (candidates.iter().max().unwrap() + 1) {
        return Vec::new();
    }
    let cells = image_features.len() / dim;
    let Ok(image) = ArrayView2::from_shape((dim, cells), image_features) else { return Vec::new() };
    let (points, cells_best) = score(point_features, dim, candidates, image, grid_width);
    if tracing::enabled!(tracing::Level::DEBUG) {
        let mut best: Vec<f32> = points.iter().map(|p| p.best).collect();
        let mut gap: Vec<f32> = points.iter().map(|p| p.best - p.second).collect();
        best.sort_by(f32::total_cmp);
        gap.sort_by(f32::total_cmp);
        let distinct = cells_best.iter().filter(|(c, _)| *c != usize::MAX).map(|(c, _)| *c).collect::<std::collections::BTreeSet<_>>().len();
        tracing::debug!(candidates = points.len(), median_best = best[best.len() / 2], median_gap = gap[gap.len() / 2], distinct_points_chosen_by_cells = distinct, "matching similarity");
    }
    let matched = points.iter().enumerate().filter(|(_, pb)| pb.best.is_finite());
    match strategy {
        MatchStrategy::Mutual => matched
            .filter(|(candidate, pb)| cells_best[pb.cell].0 == *candidate)
            .map(|(candidate, pb)| FeatureMatch { point: candidates[candidate], cell: pb.cell, similarity: pb.best })
            .collect(),
        MatchStrategy::Ratio => {
            let distance = |s: f32| (2.0 - 2.0 * s).max(0.0).sqrt();
            let mut kept: Vec<FeatureMatch> = matched
                .filter(|(_, pb)| !pb.second.is_finite() || distance(pb.best) < RATIO * distance(pb.second))
                .map(|(candidate, pb)| FeatureMatch { point: candidates[candidate], cell: pb.cell, similarity: pb.best })
                .collect();
            kept.sort_by(|a, b| b.similarity.total_cmp(&a.similarity).then(a.point.cmp(&b.point)));
            kept.truncate(MAX_RATIO_MATCHES);
            kept
        }
    }
}

/// The pixel (in the model's crop) at the centre of a feature cell: cell (row, col) covers
/// pixels stride·col − 0.5 ≤ u < stride·(col + 1) − 0.5, whose centre is stride·col + (stride − 1)/2.
pub fn cell_centre(cell: usize, grid_width: usize, stride: usize) -> (f64, f64) {
    let (row, col) = (cell / grid_width, cell % grid_width);
    let half = (stride as f64 - 1.0) / 2.0;
    ((stride * col) as f64 + half, (stride * row) as f64 + half)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn finds_planted_pairs_and_drops_non_mutual_ones() {
        // dim 4, 6 cells; image cell c has the unit vector e_(c % 4) scaled by c-dependent weights.
        let dim = 4;
        let cells = 6;
        let mut image = vec![0f32; dim * cells];
        for c in 0..4 {
            image[c * cells + c] = 1.0; // channel c of cell c
        }
        image[cells + 5] = 0.6; // cell 5 resembles e_1 less than cell 1 does
        image[2 * cells + 5] = 0.8;
        // Points: e_0, e_1, e_2, e_3 and a second, weaker e_2-like point.
        let points: Vec<f32> = [[1., 0., 0., 0.], [0., 1., 0., 0.], [0., 0., 1., 0.], [0., 0., 0., 1.], [0., 0.6, 0.8, 0.]]
            .concat();
        let all: Vec<usize> = (0..5).collect();
        let matches = mutual_nearest(&points, dim, &all, &image);
        let pairs: Vec<(usize, usize)> = matches.iter().map(|m| (m.point, m.cell)).collect();
        assert_eq!(pairs, vec![(0, 0), (1, 1), (2, 2), (3, 3), (4, 5)]);
        // Restricting the candidates restricts the answer and keeps original point indices.
        let some = mutual_nearest(&points, dim, &[3, 4], &image);
        assert_eq!(some.iter().map(|m| m.point).collect::<Vec<_>>(), vec![3, 4]);
        assert!(mutual_nearest(&points, dim, &[], &image).is_empty());
        // Ratio test: point 4 (best 1.0 at cell 5, second 0.8 at cell 2) passes, point 1
        // (best 1.0 at cell 1, second 0.6 at cell 5) passes, all are one-to-one here.
        let ratio = find_matches(&points, dim, &all, &image, 1, MatchStrategy::Ratio);
        let mut pairs: Vec<(usize, usize)> = ratio.iter().map(|m| (m.point, m.cell)).collect();
        pairs.sort();
        assert_eq!(pairs, vec![(0, 0), (1, 1), (2, 2), (3, 3), (4, 5)]);
        // A point equally close to cells 0 and 3 fails the ratio test when the two cells are
        // far apart (one row of 6: 3 columns apart), and passes when they are neighbours (two
        // rows of 3: cell 3 sits right below cell 0), since a neighbour is no rival.
        let ambiguous = [0.5f32.sqrt(), 0.0, 0.0, 0.5f32.sqrt()];
        assert!(find_matches(&ambiguous, dim, &[0], &image, 6, MatchStrategy::Ratio).is_empty());
        assert_eq!(find_matches(&ambiguous, dim, &[0], &image, 3, MatchStrategy::Ratio).len(), 1);
    }

    #[test]
    fn blocks_agree_with_a_single_pass() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(2);
        let (dim, cells, n) = (8, 50, 2500);
        let image: Vec<f32> = (0..dim * cells).map(|_| rng.random_range(-1.0..1.0)).collect();
        let points: Vec<f32> = (0..dim * n).map(|_| rng.random_range(-1.0..1.0)).collect();
        let all: Vec<usize> = (0..n).collect();
        let matches = mutual_nearest(&points, dim, &all, &image);
        // Brute force.
        let sim = |p: usize, c: usize| (0..dim).map(|k| points[p * dim + k] * image[k * cells + c]).sum::<f32>();
        let best_cell = |p: usize| (0..cells).max_by(|&a, &b| sim(p, a).total_cmp(&sim(p, b))).unwrap();
        let best_point = |c: usize| (0..n).max_by(|&a, &b| sim(a, c).total_cmp(&sim(b, c))).unwrap();
        let expected: Vec<(usize, usize)> = (0..n).filter(|&p| best_point(best_cell(p)) == p).map(|p| (p, best_cell(p))).collect();
        assert_eq!(matches.iter().map(|m| (m.point, m.cell)).collect::<Vec<_>>(), expected);
    }

    #[test]
    fn cell_centres_follow_the_projection_convention() {
        assert_eq!(cell_centre(0, 128, 4), (1.5, 1.5));
        assert_eq!(cell_centre(128 + 2, 128, 4), (9.5, 5.5));
    }
}
