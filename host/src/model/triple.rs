//! The common syntax of the model's flag values: three comma-separated numbers (`I,J,K`,
//! `NX,NY,NZ`, `FX,FY,FZ`). Each flag type wraps [`TripleError`] in its own error that says what
//! the three values mean, so a message always names the expected form.

use std::str::FromStr;

/// Why a comma-separated triple did not parse.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum TripleError {
    #[error("expected three comma-separated values, got {found}")]
    WrongCount { found: usize },
    #[error("value {position} ('{text}') is not {expected}")]
    BadValue {
        /// 1-based position of the offending value.
        position: usize,
        text: String,
        expected: &'static str,
    },
}

/// Splits `text` at commas and parses each of the three parts as `T`. `expected` describes one
/// value for the error message ("a non-negative integer", "a number").
pub fn parse_triple<T: FromStr>(text: &str, expected: &'static str) -> Result<[T; 3], TripleError> {
    let parts: Vec<&str> = text.split(',').map(str::trim).collect();
    if parts.len() != 3 {
        return Err(TripleError::WrongCount { found: parts.len() });
    }
    let parse = |position: usize| {
        parts[position]
            .parse::<T>()
            .map_err(|_| TripleError::BadValue {
                position: position + 1,
                text: parts[position].to_string(),
                expected,
            })
    };
    Ok([parse(0)?, parse(1)?, parse(2)?])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_three_values_with_optional_spaces() {
        assert_eq!(parse_triple::<u32>("1, 2,3", "an integer"), Ok([1, 2, 3]));
        assert_eq!(
            parse_triple::<f64>("-1.5,0,2e3", "a number"),
            Ok([-1.5, 0.0, 2000.0])
        );
    }

    #[test]
    fn rejects_wrong_counts_and_bad_values() {
        assert_eq!(
            parse_triple::<u32>("1,2", "x"),
            Err(TripleError::WrongCount { found: 2 })
        );
        assert_eq!(
            parse_triple::<u32>("1,2,3,4", "x"),
            Err(TripleError::WrongCount { found: 4 })
        );
        assert_eq!(
            parse_triple::<u32>("1,-2,3", "a non-negative integer"),
            Err(TripleError::BadValue {
                position: 2,
                text: "-2".into(),
                expected: "a non-negative integer"
            })
        );
        assert!(matches!(
            parse_triple::<u32>("1,,3", "x"),
            Err(TripleError::BadValue { position: 2, .. })
        ));
    }
}
