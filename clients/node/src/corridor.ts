// A 1-D corridor with random episode lengths, and a tabular Q-learner for it: the
// smallest environment and learner that exercise every part of a Shape stream (two
// discrete actions, terminated and truncated episodes, Q-values for the potential term).
// The same environment and learner as clients/cpp/src/corridor.hpp.

/** Actions: 0 steps left, 1 steps right. */
export const NUM_ACTIONS = 2;

/** A small seeded generator (mulberry32): runs are reproducible from their seed. */
export class Rng {
  private state: number;

  constructor(seed: number) {
    this.state = seed >>> 0;
  }

  /** Uniform in [0, 1). */
  next(): number {
    this.state = (this.state + 0x6d2b79f5) >>> 0;
    let t = this.state;
    t = Math.imul(t ^ (t >>> 15), t | 1);
    t ^= t + Math.imul(t ^ (t >>> 7), t | 61);
    return ((t ^ (t >>> 14)) >>> 0) / 4294967296;
  }

  /** Uniform integer in [lo, hi]. */
  int(lo: number, hi: number): number {
    return lo + Math.floor(this.next() * (hi - lo + 1));
  }
}

/** What one step of the environment returned. */
export interface Step {
  nextState: number;
  reward: number;
  /** Reached the goal: no value after it. */
  terminated: boolean;
  /** Hit the episode's time limit: the value after it still counts. */
  truncated: boolean;
}

/**
 * Cells 0..length-1; an episode starts in cell 0 and terminates at the last cell with
 * reward +1 (every other step costs 0.01). Each episode draws its own time limit in
 * [length, 4 * length] and is truncated when it runs out.
 */
export class Env {
  private pos = 0;
  private t = 0;
  private limit = 0;
  private readonly rng: Rng;

  constructor(
    readonly length: number,
    seed: number,
  ) {
    this.rng = new Rng(seed);
    this.reset();
  }

  /** Starts a new episode and returns its first state. */
  reset(): number {
    this.pos = 0;
    this.t = 0;
    this.limit = this.rng.int(this.length, 4 * this.length);
    return this.pos;
  }

  get state(): number {
    return this.pos;
  }

  step(action: number): Step {
    if (action === 1) {
      this.pos += 1;
    } else if (this.pos > 0) {
      this.pos -= 1;
    }
    this.t += 1;
    const terminated = this.pos === this.length - 1;
    const truncated = !terminated && this.t >= this.limit;
    return { nextState: this.pos, reward: terminated ? 1 : -0.01, terminated, truncated };
  }
}

/** Epsilon-greedy tabular Q-learning, trained on the shaped reward. */
export class QTable {
  private readonly q: Float32Array;
  private readonly rng: Rng;

  constructor(numStates: number, seed: number) {
    this.q = new Float32Array(numStates * NUM_ACTIONS);
    this.rng = new Rng(seed);
  }

  /** Q(s, .), one value per action. */
  values(s: number): number[] {
    return Array.from(this.q.subarray(s * NUM_ACTIONS, (s + 1) * NUM_ACTIONS));
  }

  act(s: number, epsilon: number): number {
    if (this.rng.next() < epsilon) {
      return this.rng.int(0, NUM_ACTIONS - 1);
    }
    const [left, right] = this.values(s);
    return right > left ? 1 : left > right ? 0 : this.rng.int(0, 1);
  }

  learn(
    s: number,
    a: number,
    reward: number,
    next: number,
    terminated: boolean,
    gamma: number,
    lr: number,
  ): void {
    const bootstrap = terminated ? 0 : gamma * Math.max(...this.values(next));
    const i = s * NUM_ACTIONS + a;
    this.q[i] += lr * (reward + bootstrap - this.q[i]);
  }
}
