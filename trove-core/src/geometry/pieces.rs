//! Splitting one ray's object segments into pieces (SPEC §4.2): where segments overlap,
//! the union of their end points cuts the ray, and each object contributes to every piece
//! it covers. Objects sharing a piece are then composited as co-located media (§4.4).

/// The part of a ray inside one object: the first and last t ≥ 0 inside its box.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Segment {
    /// Index of the object in the scene.
    pub object: u32,
    /// Entry parameter (world distance from the eye).
    pub t_near: f64,
    /// Exit parameter.
    pub t_far: f64,
}

/// An interval of a ray with the objects covering it, as a range into the cover list that
/// [`split_into_pieces`] fills.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Piece {
    /// Start parameter.
    pub t0: f64,
    /// End parameter, > `t0`.
    pub t1: f64,
    /// Range of this piece's objects in the cover list.
    pub cover: (u32, u32),
}

/// Fills `pieces` (front to back) and `cover` (object indices, per piece) from one ray's
/// segments. Pieces of zero length are dropped; the buffers are cleared first so a thread
/// can reuse them for every ray.
pub fn split_into_pieces(segments: &[Segment], cuts: &mut Vec<f64>, pieces: &mut Vec<Piece>, cover: &mut Vec<u32>) {
    pieces.clear();
    cover.clear();
    cuts.clear();
    for s in segments {
        if s.t_far > s.t_near {
            cuts.push(s.t_near);
            cuts.push(s.t_far);
        }
    }
    cuts.sort_unstable_by(f64::total_cmp);
    cuts.dedup();
    for w in cuts.windows(2) {
        let (t0, t1) = (w[0], w[1]);
        let start = cover.len() as u32;
        cover.extend(
            segments.iter().filter(|s| s.t_far > s.t_near && s.t_near <= t0 && s.t_far >= t1).map(|s| s.object),
        );
        let end = cover.len() as u32;
        if end > start {
            pieces.push(Piece { t0, t1, cover: (start, end) });
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn split(segs: &[(u32, f64, f64)]) -> Vec<(f64, f64, Vec<u32>)> {
        let segs: Vec<Segment> =
            segs.iter().map(|&(object, t_near, t_far)| Segment { object, t_near, t_far }).collect();
        let (mut cuts, mut pieces, mut cover) = (vec![], vec![], vec![]);
        split_into_pieces(&segs, &mut cuts, &mut pieces, &mut cover);
        pieces.iter().map(|p| (p.t0, p.t1, cover[p.cover.0 as usize..p.cover.1 as usize].to_vec())).collect()
    }

    #[test]
    fn overlapping_segments_split_at_every_end_point() {
        let p = split(&[(0, 1.0, 3.0), (1, 2.0, 5.0), (2, 6.0, 7.0)]);
        assert_eq!(p, vec![(1.0, 2.0, vec![0]), (2.0, 3.0, vec![0, 1]), (3.0, 5.0, vec![1]), (6.0, 7.0, vec![2])]);
    }

    #[test]
    fn zero_length_segments_and_gaps_give_no_pieces() {
        assert_eq!(split(&[(0, 1.0, 1.0)]), vec![]);
        let p = split(&[(0, 1.0, 2.0), (1, 2.0, 2.0), (2, 2.0, 4.0)]);
        assert_eq!(p, vec![(1.0, 2.0, vec![0]), (2.0, 4.0, vec![2])]);
    }

    #[test]
    fn nested_segments() {
        let p = split(&[(0, 0.0, 10.0), (1, 4.0, 6.0)]);
        assert_eq!(p, vec![(0.0, 4.0, vec![0]), (4.0, 6.0, vec![0, 1]), (6.0, 10.0, vec![0])]);
    }
}
