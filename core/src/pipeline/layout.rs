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

/// Every board target the layout puts inside a `width` x `height` frame that was neither
/// found (`found_px`, matched to the board by [`match_board`]) nor already reported
/// (`reported_px`, e.g. detection's `skipped`), as a [`Skipped`] at its expected place: with
/// a board no target in view goes missing without a word. The expected places come from an
/// affine map fitted to the matched targets (a translation when they are fewer than three or
/// in one row), which absorbs a tilt and most of a lens's distortion.
pub fn unseen_targets(
    found_px: &[[f64; 2]],
    reported_px: &[[f64; 2]],
    board: &crate::board::Board,
    scale_um_per_px: f64,
    size: (u32, u32),
) -> Vec<super::Skipped> {
    let m = match_board(found_px, board, scale_um_per_px);
    let pairs: Vec<([f64; 2], [f64; 2])> = m
        .iter()
        .zip(found_px)
        .filter_map(|(j, p)| Some((board.targets[(*j)?].centre_um, *p)))
        .collect();
    let Some(map) = fit_board_to_image(&pairs, scale_um_per_px) else {
        return Vec::new();
    };
    let matched: Vec<usize> = m.iter().flatten().copied().collect();
    // A report within the target's own rim of the expected place is that target's.
    let (w, h) = (size.0 as f64, size.1 as f64);
    let mut out = Vec::new();
    for (j, t) in board.targets.iter().enumerate() {
        if matched.contains(&j) {
            continue;
        }
        let p = map.apply(t.centre_um);
        if !(p[0] >= 0.0 && p[1] >= 0.0 && p[0] <= w - 1.0 && p[1] <= h - 1.0) {
            continue;
        }
        let reach_px = t.outer.outer_radius_um() / scale_um_per_px;
        let near = |q: &[f64; 2]| (q[0] - p[0]).hypot(q[1] - p[1]) <= reach_px;
        if found_px.iter().any(near) || reported_px.iter().any(near) {
            continue;
        }
        out.push(super::Skipped {
            centre_px: p,
            reason: format!(
                "board target {} not found: no red ring with an inner disk where the layout puts it",
                t.name
            ),
        });
    }
    out
}

/// Board µm -> image px: `image = i0 + m (board - b0)`.
struct BoardToImage {
    b0: [f64; 2],
    i0: [f64; 2],
    m: [[f64; 2]; 2],
}

impl BoardToImage {
    fn apply(&self, p: [f64; 2]) -> [f64; 2] {
        let (x, y) = (p[0] - self.b0[0], p[1] - self.b0[1]);
        let m = self.m;
        [
            self.i0[0] + m[0][0] * x + m[0][1] * y,
            self.i0[1] + m[1][0] * x + m[1][1] * y,
        ]
    }
}

/// The map from matched (board, image) pairs: least-squares affine, or the mean translation
/// at the known scale when the pairs cannot fix one. `None` with no pairs.
fn fit_board_to_image(
    pairs: &[([f64; 2], [f64; 2])],
    scale_um_per_px: f64,
) -> Option<BoardToImage> {
    if pairs.is_empty() {
        return None;
    }
    let n = pairs.len() as f64;
    let mean = |side: usize, k: usize| {
        pairs
            .iter()
            .map(|p| if side == 0 { p.0[k] } else { p.1[k] })
            .sum::<f64>()
            / n
    };
    let b0 = [mean(0, 0), mean(0, 1)];
    let i0 = [mean(1, 0), mean(1, 1)];
    // Centred normal equations: [sxx sxy; sxy syy] a = [sxu; syu] per image coordinate.
    let (mut sxx, mut syy, mut sxy) = (0.0, 0.0, 0.0);
    let (mut su, mut sv) = ([0.0; 2], [0.0; 2]);
    for (b, i) in pairs {
        let (x, y) = (b[0] - b0[0], b[1] - b0[1]);
        let (u, v) = (i[0] - i0[0], i[1] - i0[1]);
        sxx += x * x;
        syy += y * y;
        sxy += x * y;
        su = [su[0] + x * u, su[1] + y * u];
        sv = [sv[0] + x * v, sv[1] + y * v];
    }
    let det = sxx * syy - sxy * sxy;
    let m = if pairs.len() >= 3 && det > 1e-6 * (sxx * syy).max(f64::MIN_POSITIVE) {
        let solve = |r: [f64; 2]| {
            [
                (syy * r[0] - sxy * r[1]) / det,
                (sxx * r[1] - sxy * r[0]) / det,
            ]
        };
        [solve(su), solve(sv)]
    } else {
        let s = 1.0 / scale_um_per_px;
        [[s, 0.0], [0.0, s]]
    };
    Some(BoardToImage { b0, i0, m })
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
    fn a_board_target_in_view_that_was_not_found_is_reported_at_its_place() {
        let board = crate::board::Board::paper();
        let s = 774.0;
        // All but target 3 found, the board 10 px right and 5 px down of its origin.
        let at = |j: usize| {
            let c = board.targets[j].centre_um;
            [c[0] / s + 10.0, c[1] / s + 5.0]
        };
        let found: Vec<[f64; 2]> = (0..board.targets.len())
            .filter(|&j| j != 3)
            .map(at)
            .collect();
        let unseen = unseen_targets(&found, &[], &board, s, (1280, 720));
        assert_eq!(unseen.len(), 1, "{unseen:?}");
        let want = at(3);
        let got = unseen[0].centre_px;
        assert!(
            (got[0] - want[0]).hypot(got[1] - want[1]) < 1e-6,
            "{got:?} vs {want:?}"
        );
        assert!(
            unseen[0].reason.contains(&board.targets[3].name),
            "{}",
            unseen[0].reason
        );
        // Already reported (e.g. cut by the edge): not listed twice.
        assert!(unseen_targets(&found, &[want], &board, s, (1280, 720)).is_empty());
        // Out of the frame: not in view, not listed.
        assert!(unseen_targets(&found, &[], &board, s, (100, 100))
            .iter()
            .all(|u| u.centre_px[0] < 100.0));
    }

    #[test]
    fn nothing_to_match_gives_none() {
        assert_eq!(match_layout(&[[1.0, 1.0]], &[], 774.0, 1000.0), vec![None]);
        assert!(match_layout(&[], &[[0.0, 0.0]], 774.0, 1000.0).is_empty());
    }
}
