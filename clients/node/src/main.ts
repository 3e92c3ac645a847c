// A minimal TypeScript learner against a tamrm server: creates a task, opens a Shape stream
// for a vector of corridor environments, sends one StepBatch per vector step and learns
// from the shaped rewards it gets back. Its last line is
//
//     episodes E pool_size P pool_version V
//
// E: the episodes this learner ended; P: the task's pool size after the stream closed
// (GetTask); V: the pool version of the last ShapedBatch.
//
// Usage: node dist/src/main.js ADDR [--task ID] [--envs N] [--steps N] [--seed N]
// Any non-OK gRPC status is printed with its code and message, and the exit code is 1.
import * as grpc from "@grpc/grpc-js";
import * as protoLoader from "@grpc/proto-loader";
import { randomBytes } from "node:crypto";
import * as path from "node:path";
import { parseArgs } from "node:util";

import type { ProtoGrpcType } from "../gen/shaping";
import type { CreateTaskRequest } from "../gen/tamrm/v1/CreateTaskRequest";
import type { ShapeRequest } from "../gen/tamrm/v1/ShapeRequest";
import type { ShapeResponse__Output } from "../gen/tamrm/v1/ShapeResponse";
import type { ShapingClient } from "../gen/tamrm/v1/Shaping";
import type { StepBatch } from "../gen/tamrm/v1/StepBatch";
import type { Task__Output } from "../gen/tamrm/v1/Task";
import { Env, NUM_ACTIONS, QTable, type Step } from "./corridor";

const USAGE = "ADDR [--task ID] [--envs N] [--steps N] [--seed N]";
const CORRIDOR_LENGTH = 12;
const GAMMA = 0.99;
const LEARNING_RATE = 0.2;
const EPSILON = 0.1;

/** The proto/ directory of the repository (dist/src/main.js is four levels below it). */
const PROTO_ROOT = process.env.TAMRM_PROTO_ROOT ?? path.resolve(__dirname, "../../../../proto");

/**
 * How the proto is read at run time. These MUST match the flags of the `gen` script in
 * package.json, which generates the TypeScript types from the same file: field names as
 * in the proto (snake_case), 64-bit integers as decimal strings, every scalar present
 * with its default, and a `kind` property naming the member set in each oneof.
 */
const LOADER_OPTIONS: protoLoader.Options = {
  keepCase: true,
  longs: String,
  defaults: true,
  oneofs: true,
  includeDirs: [PROTO_ROOT],
};

class UsageError extends Error {}

/** A call that ended with a non-OK status. */
class CallFailed extends Error {
  constructor(
    readonly call: string,
    readonly status: grpc.ServiceError,
  ) {
    super(`${call} failed: ${grpc.status[status.code] ?? status.code}: ${status.details}`);
  }
}

/** An answer that breaks the stream's rules (SPEC §7). */
class ProtocolError extends Error {}

interface Options {
  address: string;
  taskId: string;
  envs: number;
  steps: number;
  seed: number;
}

function integer(flag: string, text: string | undefined, fallback: number, min: number): number {
  if (text === undefined) {
    return fallback;
  }
  const value = Number(text);
  if (!/^\d+$/.test(text) || !Number.isSafeInteger(value) || value < min) {
    throw new UsageError(`--${flag} takes an integer >= ${min}, got '${text}'`);
  }
  return value;
}

function parse(argv: string[]): Options {
  let parsed;
  try {
    parsed = parseArgs({
      args: argv,
      allowPositionals: true,
      options: {
        task: { type: "string" },
        envs: { type: "string" },
        steps: { type: "string" },
        seed: { type: "string" },
      },
    });
  } catch (err) {
    throw new UsageError((err as Error).message);
  }
  const { values, positionals } = parsed;
  if (positionals.length !== 1) {
    throw new UsageError(
      positionals.length === 0
        ? "the server address (host:port) is missing"
        : `unexpected argument '${positionals[1]}'`,
    );
  }
  return {
    address: positionals[0],
    taskId: values.task ?? `examples/node/${randomBytes(8).toString("hex")}`,
    envs: integer("envs", values.envs, 8, 1),
    steps: integer("steps", values.steps, 2000, 1),
    seed: integer("seed", values.seed, 1, 0),
  };
}

function connect(address: string): ShapingClient {
  const definition = protoLoader.loadSync("tamrm/v1/shaping.proto", LOADER_OPTIONS);
  const proto = grpc.loadPackageDefinition(definition) as unknown as ProtoGrpcType;
  return new proto.tamrm.v1.Shaping(address, grpc.credentials.createInsecure());
}

/**
 * Runs one unary call, started by `start` with the call options (a 10 s deadline) and the
 * completion callback; a non-OK status rejects with CallFailed.
 */
function unary<Res>(
  name: string,
  start: (options: grpc.CallOptions, done: grpc.requestCallback<Res>) => unknown,
): Promise<Res> {
  return new Promise((resolve, reject) => {
    start({ deadline: Date.now() + 10_000 }, (err, res) => {
      if (err) {
        reject(new CallFailed(name, err));
      } else if (res === undefined) {
        reject(new ProtocolError(`${name} answered nothing`));
      } else {
        resolve(res);
      }
    });
  });
}

function isServiceError(err: unknown): err is grpc.ServiceError {
  return err instanceof Error && typeof (err as Partial<grpc.ServiceError>).code === "number";
}

/**
 * A Shape stream driven in lock step: each request is answered before the next is sent.
 * A stream the server ends with a status rejects with CallFailed.
 */
class ShapeStream {
  private readonly call: grpc.ClientDuplexStream<ShapeRequest, ShapeResponse__Output>;
  private readonly answers: AsyncIterator<ShapeResponse__Output>;

  constructor(client: ShapingClient) {
    this.call = client.Shape();
    this.answers = this.call[Symbol.asyncIterator]();
  }

  async exchange(req: ShapeRequest): Promise<ShapeResponse__Output> {
    this.call.write(req);
    const next = await this.read();
    if (next.done) {
      throw new ProtocolError("the stream ended before answering a request");
    }
    return next.value;
  }

  /** Half-closes the stream and waits for the server to end it with OK. */
  async close(): Promise<void> {
    this.call.end();
    if (!(await this.read()).done) {
      throw new ProtocolError("an answer after the last batch");
    }
  }

  private async read(): Promise<IteratorResult<ShapeResponse__Output>> {
    try {
      return await this.answers.next();
    } catch (err) {
      throw isServiceError(err) ? new CallFailed("Shape", err) : err;
    }
  }
}

async function run(opt: Options): Promise<void> {
  const client = connect(opt.address);
  const request: CreateTaskRequest = {
    task_id: opt.taskId,
    config: {
      num_actions: NUM_ACTIONS,
      pool_capacity: 16,
      k: 4,
      start_step: 2,
      min_pool_size: 4,
      gamma: GAMMA,
    },
  };
  const task = await unary<Task__Output>("CreateTask", (options, done) =>
    client.CreateTask(request, options, done),
  );
  const config = task.config;
  console.log(
    `task ${task.task_id} (k ${config?.k}, alpha ${config?.alpha}, beta ${config?.beta})`,
  );

  const envs = Array.from(
    { length: opt.envs },
    (_, i) => new Env(CORRIDOR_LENGTH, opt.seed * 1000 + i),
  );
  const q = new QTable(CORRIDOR_LENGTH, opt.seed);

  const stream = new ShapeStream(client);
  const opened = await stream.exchange({ open: { task_id: task.task_id, num_envs: opt.envs } });
  if (opened.kind !== "opened") {
    throw new ProtocolError("the first answer is not `opened`");
  }

  let episodes = 0;
  let poolVersion = "0";
  const returns = new Array<number>(opt.envs).fill(0);
  const recent: number[] = []; // the last 100 episode returns, for the progress lines
  for (let t = 1; t <= opt.steps; t++) {
    // One entry per environment, in env order (env_ids left empty: entry i is env i).
    const states = envs.map((env) => env.state);
    const actions = states.map((s) => q.act(s, EPSILON));
    const outcomes: Step[] = envs.map((env, i) => env.step(actions[i]));
    const batch: StepBatch = {
      actions,
      rewards: outcomes.map((o) => o.reward),
      terminated: outcomes.map((o) => o.terminated),
      truncated: outcomes.map((o) => o.truncated),
      q_values: states.flatMap((s) => q.values(s)),
      next_q_values: outcomes.flatMap((o) => q.values(o.nextState)),
    };
    const resp = await stream.exchange({ steps: batch });
    const shaped = resp.shaped;
    if (resp.kind !== "shaped" || !shaped || shaped.rewards.length !== opt.envs) {
      throw new ProtocolError(
        `batch ${t} is not answered by one \`shaped\` with ${opt.envs} rewards`,
      );
    }
    poolVersion = shaped.pool_version;
    outcomes.forEach((out, i) => {
      const reward = shaped.rewards[i];
      q.learn(states[i], actions[i], reward, out.nextState, out.terminated, GAMMA, LEARNING_RATE);
      returns[i] += out.reward;
      if (out.terminated || out.truncated) {
        episodes += 1;
        recent.push(returns[i]);
        if (recent.length > 100) {
          recent.shift();
        }
        returns[i] = 0;
        envs[i].reset();
      }
    });
    if (t % 500 === 0 || t === opt.steps) {
      const mean = recent.length ? recent.reduce((a, b) => a + b, 0) / recent.length : 0;
      console.log(
        `step ${t}/${opt.steps} episodes ${episodes} mean_return(last 100) ${mean.toFixed(4)}` +
          ` pool_version ${poolVersion}`,
      );
    }
  }
  await stream.close();

  const after = await unary<Task__Output>("GetTask", (options, done) =>
    client.GetTask({ task_id: task.task_id }, options, done),
  );
  const poolSize = after.stats?.pool_size ?? 0;
  console.log(`episodes ${episodes} pool_size ${poolSize} pool_version ${poolVersion}`);
  client.close();
}

async function main(): Promise<number> {
  try {
    await run(parse(process.argv.slice(2)));
    return 0;
  } catch (err) {
    if (err instanceof UsageError) {
      console.error(`tamrm_learner: ${err.message}`);
      console.error(`usage: node dist/src/main.js ${USAGE}`);
      return 2;
    }
    if (err instanceof CallFailed) {
      console.error(`tamrm_learner: ${err.message}`);
      return 1;
    }
    if (err instanceof ProtocolError) {
      console.error(`tamrm_learner: unexpected answer from the server: ${err.message}`);
      return 1;
    }
    throw err;
  }
}

main().then((code) => {
  process.exitCode = code;
});
