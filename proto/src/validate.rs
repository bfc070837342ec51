//! Field-path validation errors: `lights[0].intensity[1] must be finite and in [0, 1000000000000]`.

use std::fmt;

/// A value that broke a rule, with the path of the field that holds it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FieldError {
    /// Dotted path with indices, e.g. `objects[2].material.albedo[0]`.
    pub path: String,
    /// The rule, phrased to follow the path: `must be in [0, 1]`.
    pub rule: String,
}

impl FieldError {
    pub fn new(path: impl Into<String>, rule: impl Into<String>) -> Self {
        Self {
            path: path.into(),
            rule: rule.into(),
        }
    }
}

impl fmt::Display for FieldError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{} {}", self.path, self.rule)
    }
}

impl std::error::Error for FieldError {}

/// `v` must be finite.
pub fn check_finite(path: &str, v: f32) -> Result<(), FieldError> {
    if v.is_finite() {
        Ok(())
    } else {
        Err(FieldError::new(path, "must be finite"))
    }
}

/// `v` must be finite and within `[lo, hi]`.
pub fn check_range(path: &str, v: f32, lo: f32, hi: f32) -> Result<(), FieldError> {
    if v.is_finite() && v >= lo && v <= hi {
        return Ok(());
    }
    let rule = if hi == f32::MAX {
        format!("must be finite and >= {lo}")
    } else {
        format!("must be finite and in [{lo}, {hi}]")
    };
    Err(FieldError::new(path, rule))
}

/// Every component finite.
pub fn check_vec_finite(path: &str, v: &[f32]) -> Result<(), FieldError> {
    for (k, x) in v.iter().enumerate() {
        check_finite(&format!("{path}[{k}]"), *x)?;
    }
    Ok(())
}

/// Every component finite and within `[lo, hi]`.
pub fn check_vec_range(path: &str, v: &[f32], lo: f32, hi: f32) -> Result<(), FieldError> {
    for (k, x) in v.iter().enumerate() {
        check_range(&format!("{path}[{k}]"), *x, lo, hi)?;
    }
    Ok(())
}

/// A non-zero, finite direction.
pub fn check_direction(path: &str, v: &[f32; 3]) -> Result<(), FieldError> {
    check_vec_finite(path, v)?;
    if v.iter().map(|x| x * x).sum::<f32>() <= 1e-20 {
        return Err(FieldError::new(path, "must be a non-zero vector"));
    }
    Ok(())
}
