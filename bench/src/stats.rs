//! The one `median` every experiment reports, so that two tables of the same runs never
//! disagree by which middle value each picked, and the run a table shows as the median
//! run ([`median_run`]), chosen by it.

use trove_core::render::Rendered;

/// The median of `values`: for an even count, the mean of the two middle values, so that
/// it leans towards neither the slower nor the faster of them; `None` for none. Sorting uses `f64::total_cmp`, so a NaN (a failed measurement's ratio) cannot
/// panic the sort: it sorts above every number (below, if negative) and only moves the
/// middle.
pub fn median(values: impl IntoIterator<Item = f64>) -> Option<f64> {
    let mut v: Vec<f64> = values.into_iter().collect();
    v.sort_by(f64::total_cmp);
    let n = v.len();
    match n {
        0 => None,
        _ if n % 2 == 1 => Some(v[n / 2]),
        _ => Some((v[n / 2 - 1] + v[n / 2]) / 2.0),
    }
}

/// The run with the median total time of `runs`: the middle one for an odd count; for an
/// even count, whose [`median`] is the mean of the two middle times, the slower of those two
/// runs (a run cannot be averaged, and the slower one does not flatter).
///
/// # Panics
/// If `runs` is empty (every caller renders at least once).
pub fn median_run(runs: Vec<Rendered>) -> Rendered {
    median_item(runs, |r| r.stats.seconds.total).expect("at least one run")
}

/// The item of `items` whose `key` is the median, as [`median_run`] picks it.
fn median_item<T>(mut items: Vec<T>, key: impl Fn(&T) -> f64) -> Option<T> {
    if items.is_empty() {
        return None;
    }
    items.sort_by(|a, b| key(a).total_cmp(&key(b)));
    let middle = items.len() / 2;
    Some(items.swap_remove(middle))
}

#[cfg(test)]
mod tests {
    use super::{median, median_item};

    #[test]
    fn the_median_item_is_the_middle_one_or_the_slower_of_the_two_middle_ones() {
        assert_eq!(median_item(vec![3.0, 1.0, 2.0], |&x| x), Some(2.0));
        assert_eq!(median_item(vec![4.0, 1.0, 3.0, 2.0], |&x| x), Some(3.0));
        assert_eq!(median_item(Vec::<f64>::new(), |&x| x), None);
    }

    #[test]
    fn an_odd_count_gives_the_middle_value_whatever_the_order() {
        assert_eq!(median([3.0, 1.0, 2.0]), Some(2.0));
        assert_eq!(median([5.0]), Some(5.0));
    }

    #[test]
    fn an_even_count_gives_the_mean_of_the_two_middle_values() {
        assert_eq!(median([4.0, 1.0, 3.0, 2.0]), Some(2.5));
        assert_eq!(median([1.0, 2.0]), Some(1.5));
    }

    #[test]
    fn no_values_give_none() {
        assert_eq!(median(std::iter::empty()), None);
    }

    #[test]
    fn a_nan_sorts_last_instead_of_panicking() {
        assert_eq!(median([f64::NAN, 1.0, 2.0]), Some(2.0));
        assert!(median([f64::NAN, 1.0]).unwrap().is_nan());
    }
}
