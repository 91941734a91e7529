//! Naming the targets found: match their layout to a board's with the known scale and no
//! prior position of the board in the image.
//!
//! Every (found target, board target) pair proposes a translation between the image (in µm,
//! centre_px x scale) and the board; the one that brings the most targets within
//! `tolerance_um` of a board target wins (ties: the smaller residual), then each found
//! target takes the nearest board target within tolerance. A roll of the board of a degree
//! or so moves targets far from the anchor by a few mm, inside the tolerance.

/// For each found centre (image px), the index of the board target it matches, if any.
pub fn match_layout(
    found_px: &[[f64; 2]],
    board_um: &[[f64; 2]],
    scale_um_per_px: f64,
    tolerance_um: f64,
) -> Vec<Option<usize>> {
    let found_um: Vec<[f64; 2]> = found_px
        .iter()
        .map(|p| [p[0] * scale_um_per_px, p[1] * scale_um_per_px])
        .collect();
    let score = |t: [f64; 2]| -> (usize, f64) {
        let mut n = 0;
        let mut r = 0.0;
        for f in &found_um {
            let d = board_um
                .iter()
                .map(|b| (f[0] + t[0] - b[0]).hypot(f[1] + t[1] - b[1]))
                .fold(f64::INFINITY, f64::min);
            if d <= tolerance_um {
                n += 1;
                r += d * d;
            }
        }
        (n, r)
    };
    let mut best: Option<([f64; 2], usize, f64)> = None;
    for f in &found_um {
        for b in board_um {
            let t = [b[0] - f[0], b[1] - f[1]];
            let (n, r) = score(t);
            let better = match best {
                None => true,
                Some((_, bn, br)) => n > bn || (n == bn && r < br),
            };
            if better {
                best = Some((t, n, r));
            }
        }
    }
    let Some((t, n, _)) = best else {
        return vec![None; found_px.len()];
    };
    if n == 0 {
        return vec![None; found_px.len()];
    }
    // Nearest board target within tolerance, each board target used once (closest wins).
    let mut cand: Vec<(f64, usize, usize)> = Vec::new();
    for (i, f) in found_um.iter().enumerate() {
        for (j, b) in board_um.iter().enumerate() {
            let d = (f[0] + t[0] - b[0]).hypot(f[1] + t[1] - b[1]);
            if d <= tolerance_um {
                cand.push((d, i, j));
            }
        }
    }
    cand.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut out = vec![None; found_px.len()];
    let mut used = vec![false; board_um.len()];
    for (_, i, j) in cand {
        if out[i].is_none() && !used[j] {
            out[i] = Some(j);
            used[j] = true;
        }
    }
    out
}

/// The board's target for each found one (outer centres, image px): [`match_layout`] within
/// half the board's smallest ring hole, so a target cannot be taken for its neighbour.
pub fn match_board(
    found_px: &[[f64; 2]],
    board: &crate::board::Board,
    scale_um_per_px: f64,
) -> Vec<Option<usize>> {
    let centres: Vec<[f64; 2]> = board.targets.iter().map(|t| t.centre_um).collect();
    let tol = board
        .targets
        .iter()
        .map(|t| match t.outer {
            crate::board::Shape::Ring {
                inner_radius_um, ..
            } => inner_radius_um,
            crate::board::Shape::Disk { radius_um } => radius_um,
        })
        .fold(f64::INFINITY, f64::min)
        * 0.5;
    match_layout(found_px, &centres, scale_um_per_px, tol)
}

/// The board's name for each found target ([`match_board`]: the tolerance the pipeline
/// names its results with).
pub fn name_targets(
    found_px: &[[f64; 2]],
    board: &crate::board::Board,
    scale_um_per_px: f64,
) -> Vec<Option<String>> {
    match_board(found_px, board, scale_um_per_px)
        .into_iter()
        .map(|j| j.map(|j| board.targets[j].name.clone()))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn finds_the_translation_and_names_a_subset() {
        let board = [
            [0.0, 0.0],
            [10_000.0, 0.0],
            [20_000.0, 0.0],
            [0.0, 30_000.0],
        ];
        // Three of the four found, shifted by an unknown offset, plus a stray detection.
        let s = 774.0;
        let off = [123_456.0, 78_900.0];
        let mut found: Vec<[f64; 2]> = [1, 3, 2]
            .iter()
            .map(|&j: &usize| [(board[j][0] + off[0]) / s, (board[j][1] + off[1]) / s])
            .collect();
        found.push([0.0, 0.0]);
        let m = match_layout(&found, &board, s, 3000.0);
        assert_eq!(m, vec![Some(1), Some(3), Some(2), None]);
    }

    #[test]
    fn nothing_to_match_gives_none() {
        assert_eq!(match_layout(&[[1.0, 1.0]], &[], 774.0, 1000.0), vec![None]);
        assert!(match_layout(&[], &[[0.0, 0.0]], 774.0, 1000.0).is_empty());
    }
}
