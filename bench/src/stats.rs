//! The one `median` every experiment reports, so that two tables of the same runs never
//! disagree by which middle value each picked.

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

#[cfg(test)]
mod tests {
    use super::median;

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
