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

/// Rows of the point-feature matrix multiplied at once: 4096 × 5120 cells × 4 B = 84 MB.
const BLOCK: usize = 4096;

/// Mutual nearest neighbours between `candidates` (indices of rows of `point_features`,
/// [N, dim] row-major) and the cells of `image_features` ([dim, cells] channel-major).
pub fn mutual_nearest(point_features: &[f32], dim: usize, candidates: &[usize], image_features: &[f32]) -> Vec<FeatureMatch> {
    if dim == 0 || candidates.is_empty() || image_features.len() % dim != 0 {
        return Vec::new();
    }
    let cells = image_features.len() / dim;
    let Ok(image) = ArrayView2::from_shape((dim, cells), image_features) else { return Vec::new() };
    let mut best_cell_of_point: Vec<(usize, f32)> = Vec::with_capacity(candidates.len());
    let mut best_point_of_cell: Vec<(usize, f32)> = vec![(usize::MAX, f32::NEG_INFINITY); cells];
    for (block_index, block) in candidates.chunks(BLOCK).enumerate() {
        let mut rows = Array2::<f32>::zeros((block.len(), dim));
        for (r, &p) in block.iter().enumerate() {
            rows.row_mut(r).assign(&ndarray::ArrayView1::from(&point_features[p * dim..(p + 1) * dim]));
        }
        let similarity = rows.dot(&image);
        for (r, row) in similarity.outer_iter().enumerate() {
            let candidate = block_index * BLOCK + r;
            let mut best = (0usize, f32::NEG_INFINITY);
            for (c, &s) in row.iter().enumerate() {
                if s > best.1 {
                    best = (c, s);
                }
                if s > best_point_of_cell[c].1 {
                    best_point_of_cell[c] = (candidate, s);
                }
            }
            best_cell_of_point.push(best);
        }
    }
    best_cell_of_point
        .iter()
        .enumerate()
        .filter(|(candidate, (cell, s))| s.is_finite() && best_point_of_cell[*cell].0 == *candidate)
        .map(|(candidate, &(cell, similarity))| FeatureMatch { point: candidates[candidate], cell, similarity })
        .collect()
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
    }

    #[test]
    fn cell_centres_follow_the_projection_convention() {
        assert_eq!(cell_centre(0, 128, 4), (1.5, 1.5));
        assert_eq!(cell_centre(128 + 2, 128, 4), (9.5, 5.5));
    }
}
