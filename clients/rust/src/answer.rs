//! The answer to one step, whichever transport gave it.

use tamrm::proto;

/// The answer to one step, column by column.
#[derive(Debug, Default, Clone, PartialEq)]
pub struct Answer {
    /// The shaped rewards R_meta, one per entry.
    pub rewards: Vec<f64>,
    /// The kNN terms r(t).
    pub knn_rewards: Vec<f64>,
    /// The potential terms F.
    pub potentials: Vec<f64>,
    /// Each entry's step index t in its episode.
    pub steps: Vec<i64>,
    /// Whether the kNN term was active for the entry.
    pub knn_active: Vec<bool>,
    /// The task's pool version after the batch.
    pub pool_version: u64,
}

impl Answer {
    /// From the session layer's outputs.
    pub fn from_outputs(outputs: &[tamrm::core::StepOutput], pool_version: u64) -> Answer {
        Answer {
            rewards: outputs.iter().map(|o| o.reward).collect(),
            knn_rewards: outputs.iter().map(|o| o.knn_reward).collect(),
            potentials: outputs.iter().map(|o| o.potential).collect(),
            steps: outputs.iter().map(|o| o.step as i64).collect(),
            knn_active: outputs.iter().map(|o| o.knn_active).collect(),
            pool_version,
        }
    }

    /// From a `ShapedBatch` message.
    pub fn from_proto(msg: proto::ShapedBatch) -> Answer {
        Answer {
            rewards: msg.rewards,
            knn_rewards: msg.knn_rewards,
            potentials: msg.potentials,
            steps: msg.steps.iter().map(|&s| i64::from(s)).collect(),
            knn_active: msg.knn_active,
            pool_version: msg.pool_version,
        }
    }

    /// Entries answered, if every column has the same length.
    pub fn consistent_len(&self) -> Option<usize> {
        let n = self.rewards.len();
        (self.knn_rewards.len() == n
            && self.potentials.len() == n
            && self.steps.len() == n
            && self.knn_active.len() == n)
            .then_some(n)
    }
}
