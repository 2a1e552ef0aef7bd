//! The spring elasticity k̃ of homogeneous tissue, per displacement direction.
//!
//! Thesis 2.6 solves the x, y and z systems with different elasticities (1, 2 and 0.5 N/m), so
//! direction d uses K_d = k_d·A where A is the unit-spring Laplacian (eq. 38).

use std::fmt;
use std::str::FromStr;

use super::grid::Axis;

/// Why an elasticity is unusable or did not parse.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ElasticityError {
    #[error("expected the elasticity as K (all directions) or KX,KY,KZ, got {found} comma-separated values")]
    WrongCount { found: usize },
    #[error("elasticity value '{0}' is not a number")]
    NotANumber(String),
    #[error("elasticity k_{axis} = {value} must be finite and greater than 0")]
    NotPositive { axis: Axis, value: f64 },
}

/// k_x, k_y, k_z (N/m), each finite and positive.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Elasticity([f64; 3]);

impl Elasticity {
    pub fn new(kx: f64, ky: f64, kz: f64) -> Result<Self, ElasticityError> {
        for (axis, value) in Axis::ALL.into_iter().zip([kx, ky, kz]) {
            if !(value.is_finite() && value > 0.0) {
                return Err(ElasticityError::NotPositive { axis, value });
            }
        }
        Ok(Self([kx, ky, kz]))
    }

    /// The same k̃ in every direction.
    pub fn isotropic(k: f64) -> Result<Self, ElasticityError> {
        Self::new(k, k, k)
    }

    /// k_d for direction `axis`.
    pub fn along(self, axis: Axis) -> f64 {
        self.0[axis.position()]
    }
}

impl fmt::Display for Elasticity {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let [kx, ky, kz] = self.0;
        write!(f, "k_x = {kx}, k_y = {ky}, k_z = {kz} N/m")
    }
}

impl FromStr for Elasticity {
    type Err = ElasticityError;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        let values = text
            .split(',')
            .map(|part| {
                let part = part.trim();
                part.parse::<f64>()
                    .map_err(|_| ElasticityError::NotANumber(part.to_string()))
            })
            .collect::<Result<Vec<f64>, _>>();
        let count = text.split(',').count();
        match (count, values) {
            (1 | 3, Err(e)) => Err(e),
            (1, Ok(v)) => Self::isotropic(v[0]),
            (3, Ok(v)) => Self::new(v[0], v[1], v[2]),
            (found, _) => Err(ElasticityError::WrongCount { found }),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_one_or_three_values() {
        let e: Elasticity = "1,2,0.5".parse().unwrap();
        assert_eq!(
            [e.along(Axis::X), e.along(Axis::Y), e.along(Axis::Z)],
            [1.0, 2.0, 0.5]
        );
        assert_eq!("3".parse(), Elasticity::isotropic(3.0));
    }

    #[test]
    fn refuses_bad_values() {
        assert_eq!(
            "1,2".parse::<Elasticity>(),
            Err(ElasticityError::WrongCount { found: 2 })
        );
        assert_eq!(
            "1,2,3,4".parse::<Elasticity>(),
            Err(ElasticityError::WrongCount { found: 4 })
        );
        assert_eq!(
            "1,x,3".parse::<Elasticity>(),
            Err(ElasticityError::NotANumber("x".into()))
        );
        assert_eq!(
            "".parse::<Elasticity>(),
            Err(ElasticityError::NotANumber("".into()))
        );
        assert_eq!(
            "1,0,3".parse::<Elasticity>(),
            Err(ElasticityError::NotPositive {
                axis: Axis::Y,
                value: 0.0
            })
        );
        assert!(matches!(
            "-1".parse::<Elasticity>(),
            Err(ElasticityError::NotPositive { .. })
        ));
        assert!(matches!(
            "1,1,inf".parse::<Elasticity>(),
            Err(ElasticityError::NotPositive { .. })
        ));
        assert!(matches!(
            "nan".parse::<Elasticity>(),
            Err(ElasticityError::NotPositive { .. })
        ));
        let message = "1,-2,3".parse::<Elasticity>().unwrap_err().to_string();
        assert!(
            message.contains("k_y") && message.contains("greater than 0"),
            "{message}"
        );
    }
}
