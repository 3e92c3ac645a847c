// A 1-D corridor with random episode lengths, and a tabular Q-learner for it: the
// smallest environment and learner that exercise every part of a Shape stream (two
// discrete actions, terminated and truncated episodes, Q-values for the potential term).
#pragma once

#include <array>
#include <cstdint>
#include <random>
#include <vector>

namespace corridor {

/// Actions: 0 steps left, 1 steps right.
constexpr uint32_t kNumActions = 2;

/// What one step of the environment returned.
struct Step {
    uint32_t next_state;
    double reward;
    bool terminated;  // reached the goal: no value after it
    bool truncated;   // hit the episode's time limit: the value after it still counts
};

/// Cells 0..length-1; an episode starts in cell 0 and terminates at the last cell with
/// reward +1 (every other step costs 0.01). Each episode draws its own time limit in
/// [length, 4 * length] and is truncated when it runs out.
class Env {
  public:
    Env(uint32_t length, uint64_t seed) : length_(length), rng_(seed) { reset(); }

    /// Starts a new episode and returns its first state.
    uint32_t reset() {
        pos_ = 0;
        t_ = 0;
        limit_ = std::uniform_int_distribution<uint32_t>(length_, 4 * length_)(rng_);
        return pos_;
    }

    uint32_t state() const { return pos_; }
    uint32_t num_states() const { return length_; }

    Step step(uint32_t action) {
        if (action == 1) {
            pos_ += 1;
        } else if (pos_ > 0) {
            pos_ -= 1;
        }
        t_ += 1;
        const bool terminated = pos_ == length_ - 1;
        const bool truncated = !terminated && t_ >= limit_;
        return Step{pos_, terminated ? 1.0 : -0.01, terminated, truncated};
    }

  private:
    uint32_t length_;
    std::mt19937_64 rng_;
    uint32_t pos_ = 0;
    uint32_t t_ = 0;
    uint32_t limit_ = 0;
};

/// Epsilon-greedy tabular Q-learning, trained on the shaped reward.
class QTable {
  public:
    QTable(uint32_t num_states, uint64_t seed) : q_(num_states), rng_(seed) {}

    const std::array<float, kNumActions>& values(uint32_t s) const { return q_[s]; }

    uint32_t act(uint32_t s, double epsilon) {
        if (std::uniform_real_distribution<double>(0.0, 1.0)(rng_) < epsilon) {
            return std::uniform_int_distribution<uint32_t>(0, kNumActions - 1)(rng_);
        }
        return q_[s][1] > q_[s][0] ? 1 : (q_[s][0] > q_[s][1] ? 0 : coin());
    }

    void learn(uint32_t s, uint32_t a, double reward, uint32_t next, bool terminated,
               double gamma, double lr) {
        const double bootstrap = terminated ? 0.0 : gamma * max_value(next);
        q_[s][a] += static_cast<float>(lr * (reward + bootstrap - q_[s][a]));
    }

  private:
    double max_value(uint32_t s) const { return q_[s][0] > q_[s][1] ? q_[s][0] : q_[s][1]; }
    uint32_t coin() { return std::uniform_int_distribution<uint32_t>(0, 1)(rng_); }

    std::vector<std::array<float, kNumActions>> q_;
    std::mt19937_64 rng_;
};

}  // namespace corridor
