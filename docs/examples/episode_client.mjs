#!/usr/bin/env node
// Drive one ParkSim scenario over HTTP (docs/episode_api.md) with Node.js >= 18 and nothing else (built-in fetch).
//
//   PARKSIM_API_KEY=... node episode_client.mjs SCENARIO.yaml [--url http://127.0.0.1:8000]
//       [--policy "0.3,0;0.3,0.5;0,0"] [--max-steps N] [--cameras front,rear] [--bev] [--jpeg]
//
// SCENARIO is a scenario file: a .json file is sent as its object, any other (YAML) as its text, which the server
// parses. The policy is a list of [acceleration, steering] actions in [-1, 1], applied one per step with the last
// held (default: creep forward, "0.2,0"). Prints one JSON line per step ({"step", "reward", "done", "truncated",
// "distance"}) and a last line with the scorecard ({"id", "scenario", "done", "scorecard"}), then deletes the
// episode. The API key, if the server needs one, comes from PARKSIM_API_KEY (not a flag: flags show in `ps`).
// Exit status: 0 done, 1 an HTTP error (its one-line detail on stderr), 2 bad arguments.

import { readFile } from "node:fs/promises";
import { parseArgs } from "node:util";

const USAGE = "usage: node episode_client.mjs SCENARIO [--url URL] [--policy 'a,s;a,s'] [--max-steps N] " +
  "[--cameras a,b] [--bev] [--jpeg]";

function fail(message, status) {
  console.error(message);
  process.exit(status);
}

function parsePolicy(text) {
  const actions = text.split(";").map((pair) => pair.split(",").map(Number));
  if (!actions.every((a) => a.length === 2 && a.every(Number.isFinite))) {
    fail(`--policy ${JSON.stringify(text)}: give actions as 'acceleration,steering' separated by ';'`, 2);
  }
  return actions;
}

function options() {
  let parsed;
  try {
    parsed = parseArgs({
      allowPositionals: true,
      options: {
        url: { type: "string", default: "http://127.0.0.1:8000" },
        policy: { type: "string", default: "0.2,0" },
        "max-steps": { type: "string" },
        cameras: { type: "string", default: "" },
        bev: { type: "boolean", default: false },
        jpeg: { type: "boolean", default: false },
      },
    });
  } catch (e) {
    fail(`${e.message}\n${USAGE}`, 2);
  }
  const { values, positionals } = parsed;
  if (positionals.length !== 1) fail(USAGE, 2);
  const maxSteps = values["max-steps"] === undefined ? Infinity : Number(values["max-steps"]);
  if (!(Number.isInteger(maxSteps) || maxSteps === Infinity) || maxSteps < 1) {
    fail("--max-steps must be a whole number >= 1", 2);
  }
  return {
    file: positionals[0],
    url: values.url.replace(/\/+$/, ""),
    policy: parsePolicy(values.policy),
    maxSteps,
    cameras: values.cameras.split(",").map((c) => c.trim()).filter(Boolean),
    bev: values.bev,
    imageFormat: values.jpeg ? "jpeg" : "png",
  };
}

// One request; a 503 (queue, reply budget or episode store full) is retried after its Retry-After, three times.
async function call(url, method, body) {
  const headers = { "content-type": "application/json" };
  if (process.env.PARKSIM_API_KEY) headers["x-api-key"] = process.env.PARKSIM_API_KEY;
  for (let attempt = 0; ; attempt++) {
    const reply = await fetch(url, { method, headers, body: body === undefined ? undefined : JSON.stringify(body) });
    if (reply.status === 503 && attempt < 3) {
      const wait = Number(reply.headers.get("retry-after") ?? 1);
      await new Promise((resolve) => setTimeout(resolve, 1000 * wait));
      continue;
    }
    if (reply.status === 204) return null;
    const data = await reply.json().catch(() => ({ detail: reply.statusText }));
    if (!reply.ok) fail(`${method} ${url}: ${reply.status} ${data.detail ?? JSON.stringify(data)}`, 1);
    return data;
  }
}

async function main() {
  const opts = options();
  let text;
  try {
    text = await readFile(opts.file, "utf8");
  } catch (e) {
    fail(`${opts.file}: ${e.message}`, 2);
  }
  let scenario = text;
  if (opts.file.endsWith(".json")) {
    try {
      scenario = JSON.parse(text);
    } catch (e) {
      fail(`${opts.file}: not JSON: ${e.message}`, 2);
    }
  }
  const created = await call(`${opts.url}/episodes`, "POST", {
    scenario, cameras: opts.cameras, bev: opts.bev, image_format: opts.imageFormat,
  });
  const episode = `${opts.url}/episodes/${created.id}`;
  let done = false;
  for (let step = 1; !done && step <= opts.maxSteps; step++) {
    const action = opts.policy[Math.min(step - 1, opts.policy.length - 1)];
    // A planner would read reply.observation here: state, and images as base64 PNG/JPEG per camera.
    const reply = await call(`${episode}/step`, "POST", { action });
    done = reply.done;
    console.log(JSON.stringify({ step, reward: reply.reward, done, truncated: reply.truncated,
      distance: reply.info.distance }));
  }
  console.log(JSON.stringify(await call(`${episode}/result`, "GET")));
  await call(episode, "DELETE");
}

await main();
