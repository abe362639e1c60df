//! The source recipe's learning-rate schedule: linear warm-up, then cosine decay to 1% of the
//! peak at the last step; `constant` is the recipe of the first shipped model.

use serde::{Deserialize, Serialize};
use tch::nn;

use crate::backbone::{DECODER_GROUP, TRUNK_GROUP};
use crate::error::{EngineError, Result};

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Schedule {
    Cosine,
    Constant,
}

impl std::str::FromStr for Schedule {
    type Err = EngineError;

    fn from_str(s: &str) -> Result<Self> {
        match s {
            "cosine" => Ok(Schedule::Cosine),
            "constant" => Ok(Schedule::Constant),
            _ => Err(EngineError::InvalidInput(format!("unknown schedule {s:?} (cosine or constant)"))),
        }
    }
}

/// A run's learning rates: peaks per optimiser group and the shape over its steps.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LearningRates {
    pub schedule: Schedule,
    /// Peak learning rate of the decoder (optimiser group 1).
    pub decoder: f64,
    /// Peak learning rate of the trunk (group 0): lower for a pretrained trunk.
    pub trunk: f64,
    pub warmup_steps: usize,
    pub total_steps: usize,
}

impl LearningRates {
    /// The factor of the peaks at `step`: from 1/warmup up to 1, then cosine down to 1%.
    pub fn factor(&self, step: usize) -> f64 {
        if self.schedule == Schedule::Constant {
            return 1.0;
        }
        let warmup = self.warmup_steps.max(1);
        if step < warmup {
            return (step + 1) as f64 / warmup as f64;
        }
        let t = (step - warmup) as f64 / self.total_steps.saturating_sub(warmup).max(1) as f64;
        0.01 + 0.99 * 0.5 * (1.0 + (std::f64::consts::PI * t.min(1.0)).cos())
    }

    /// Sets both groups' rates for `step`.
    pub fn apply(&self, opt: &mut nn::Optimizer, step: usize) {
        let f = self.factor(step);
        opt.set_lr_group(TRUNK_GROUP, self.trunk * f);
        opt.set_lr_group(DECODER_GROUP, self.decoder * f);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn warm_up_then_cosine_down_to_one_percent() {
        let lr = LearningRates {
            schedule: Schedule::Cosine,
            decoder: 1e-3,
            trunk: 1e-4,
            warmup_steps: 10,
            total_steps: 110,
        };
        assert!((lr.factor(0) - 0.1).abs() < 1e-12);
        assert!((lr.factor(9) - 1.0).abs() < 1e-12);
        assert!((lr.factor(60) - (0.01 + 0.99 * 0.5)).abs() < 1e-12);
        assert!((lr.factor(110) - 0.01).abs() < 1e-12);
        assert!(lr.factor(500) >= 0.01);
        let constant = LearningRates { schedule: Schedule::Constant, ..lr };
        assert_eq!(constant.factor(0), 1.0);
        assert_eq!("cosine".parse::<Schedule>().unwrap(), Schedule::Cosine);
        assert!("linear".parse::<Schedule>().is_err());
    }
}
