// What the TypeScript drivers share: the fixture the Python test wrote, the checks every error
// answer must pass (a Problem with the request's id), and waiting for a job. No generated code.
import assert from "node:assert/strict";
import { readFileSync } from "node:fs";

export interface Fixture {
  url: string;
  token: string;
  images: { path: string; instances: { object: string; bbox: number[] }[] }[];
  // an image of several boxes as a frame; region: its first box's crop context as raw bgr8 pixels
  frame: {
    path: string;
    instances: { object: string; bbox: number[] }[];
    width: number;
    height: number;
    region: { x_offset: number; y_offset: number; width: number; height: number; encoding: string; path: string };
  };
  whole_zip: string;
  part_zip: string;
  max_request_bytes: number;
}

export const fixture: Fixture = JSON.parse(readFileSync(process.env.CKS_FIXTURE as string, "utf-8"));
export const bytes = (path: string): Uint8Array<ArrayBuffer> => new Uint8Array(readFileSync(path));
export const base64 = (path: string): string => readFileSync(path).toString("base64");
export const blob = (data: Uint8Array<ArrayBuffer>, type: string): Blob => new Blob([data], { type });

export interface ProblemLike {
  status: number;
  detail: string;
  title: string;
  request_id?: string | null;
  errors?: string[] | null;
}

/** The error answer is the documented Problem: its status, a detail, the request's id in body and header. */
export function problem(answer: { error?: unknown; response: Response }, status: number): ProblemLike {
  assert.equal(answer.response.status, status, JSON.stringify(answer.error));
  assert.match(answer.response.headers.get("content-type") ?? "", /^application\/problem\+json/);
  const parsed = answer.error as ProblemLike;
  assert.equal(typeof parsed, "object", `not parsed: ${String(parsed)}`);
  assert.equal(parsed.status, status);
  assert.ok(parsed.title && parsed.detail, JSON.stringify(parsed));
  assert.equal(parsed.request_id, answer.response.headers.get("x-request-id"));
  seen.push(status);
  return parsed;
}

export const seen: number[] = []; // the error statuses parsed, for the Python test

export interface JobLike {
  id: string;
  state: string;
  version?: number | null;
  result?: { [key: string]: unknown } | null;
}

/** Poll a job until it ends. */
export async function finished(job: JobLike, get: (id: string) => Promise<JobLike>): Promise<JobLike> {
  for (let i = 0; i < 600; i++) {
    job = await get(job.id);
    if (["succeeded", "failed", "interrupted"].includes(job.state)) return job;
    await new Promise((resolve) => setTimeout(resolve, 200));
  }
  throw new Error(`job ${job.id} still ${job.state}`);
}

export function report(generator: string, calls: string[]): void {
  console.log(JSON.stringify({ generator, calls, problems: seen }));
}
