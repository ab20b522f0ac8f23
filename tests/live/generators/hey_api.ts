// A client generated untouched by @hey-api/openapi-ts (its fetch client and SDK functions), driven
// through predict (JSON and form), the drawing, batches, uploads (raw and form), jobs, activation,
// an audit, and typed errors, each parsed as the document's Problem.
import assert from "node:assert/strict";
import { createClient, createConfig } from "./generated/hey/client";
import * as sdk from "./generated/hey/sdk.gen";
import type { JobOut, PredictJson, PredictParameters } from "./generated/hey/types.gen";
import { base64, blob, bytes, finished, fixture, problem, report } from "./common";

const anyone = createClient(createConfig({ baseUrl: fixture.url }));
const admin = createClient(createConfig({ baseUrl: fixture.url, auth: () => fixture.token }));
const stranger = createClient(createConfig({ baseUrl: fixture.url, auth: () => "not-the-token-at-all" }));
const calls: string[] = [];

const [first, ...others] = fixture.images;
const parameters = (instances: PredictParameters["instances"]): PredictParameters => ({ instances });
const asJson = (image: (typeof fixture.images)[0], options: Partial<PredictJson> = {}): PredictJson => ({
  image_base64: base64(image.path),
  instances: image.instances as PredictJson["instances"],
  ...options,
});
const form = (image: Uint8Array<ArrayBuffer>, type = "image/jpeg") => ({
  image: blob(image, type),
  request: parameters(first.instances as PredictParameters["instances"]),
});

async function job(answer: { data?: JobOut; error?: unknown; response: Response }): Promise<JobOut> {
  assert.equal(answer.response.status, 202, JSON.stringify(answer.error));
  const get = async (id: string) => (await sdk.getJob({ client: admin, path: { job_id: id } })).data as JobOut;
  return (await finished(answer.data as JobOut, get)) as JobOut;
}

async function main(): Promise<void> {
  const model = await sdk.modelInfo({ client: anyone });
  assert.ok(model.data?.manifest.keypoints.length, "model info");
  calls.push("model_info");

  problem(await sdk.predict({ client: anyone, body: asJson(first) }), 503); // none active yet
  problem(await sdk.listCalibrations({ client: stranger }), 401);

  const zip = blob(bytes(fixture.whole_zip), "application/zip");
  const made = await job(await sdk.uploadCalibration({ client: admin, body: zip, query: { name: "first" } }));
  assert.equal(made.state, "succeeded", JSON.stringify(made));
  assert.equal(made.version, 1);
  calls.push("upload_calibration", "get_job");
  const refused = problem(await sdk.activateCalibration({ client: admin, path: { version: 1 }, body: {} }), 409);
  assert.match(refused.detail, /CKS_MIN_CALIBRATION_INSTANCES/);
  const forced = { force: true, reason: "TypeScript client test: the samples are below the floor" };
  const activated = await sdk.activateCalibration({ client: admin, path: { version: 1 }, body: forced });
  assert.equal(activated.data?.version, 1);
  calls.push("activate_calibration");

  const answer = await sdk.predict({ client: anyone, body: asJson(first) });
  assert.equal(answer.data?.instances.length, first.instances.length, JSON.stringify(answer.error));
  const viaForm = await sdk.predictForm({ client: anyone, body: form(bytes(first.path)) });
  assert.deepEqual(viaForm.data, answer.data);
  calls.push("predict", "predict_form");
  const drawing = await sdk.predictPng({ client: anyone, body: asJson(first) });
  const png = new Uint8Array(await (drawing.data as Blob).arrayBuffer());
  assert.deepEqual([...png.slice(0, 8)], [0x89, 0x50, 0x4e, 0x47, 0x0d, 0x0a, 0x1a, 0x0a]);
  const drawnForm = await sdk.predictPngForm({ client: anyone, body: form(bytes(first.path)) });
  assert.equal((drawnForm.data as Blob).size, png.length);
  calls.push("predict_png", "predict_png_form");

  const items = [first, ...others].slice(0, 3).map((image) => asJson(image));
  const batch = await sdk.predictBatch({ client: anyone, body: { items } });
  assert.deepEqual(batch.data?.items.map((item) => item.status), [200, 200, 200]);
  assert.deepEqual(batch.data?.items[0].result, answer.data);
  const formBatch = await sdk.predictBatchForm({
    client: anyone,
    body: { image_0: blob(bytes(first.path), "image/jpeg"), request_0: parameters(first.instances as never) },
  });
  assert.deepEqual(formBatch.data?.items[0].result, answer.data);
  calls.push("predict_batch", "predict_batch_form");

  const part = { file: blob(bytes(fixture.part_zip), "application/zip") };
  const second = await job(await sdk.uploadCalibrationForm({ client: admin, body: part, query: { name: "part" } }));
  assert.equal(second.version, 2, JSON.stringify(second));
  calls.push("upload_calibration_form");
  const comparison = await sdk.compareCalibration({ client: admin, path: { version: 2 } });
  assert.equal(comparison.data?.allowed, false);
  await sdk.activateCalibration({ client: admin, path: { version: 2 }, body: forced });
  const rollback = { force: true, reason: "roll back to the whole batch" };
  assert.equal((await sdk.activateCalibration({ client: admin, path: { version: 1 }, body: rollback })).data?.version, 1);
  assert.equal((await sdk.getCalibration({ client: admin, path: { version: 1 } })).data?.active, true);

  const audited = await job(await sdk.startAudit({ client: admin, body: zip, query: { version: 2, dedupe: true } }));
  assert.equal(audited.state, "succeeded", JSON.stringify(audited));
  const audit = await sdk.getAudit({ client: admin, path: { audit_id: audited.result?.audit as number } });
  assert.equal(audit.data?.version, 2);
  calls.push("start_audit", "get_audit");

  const again = { overrides: { allow_duplicate: true, reason: "the same batch again, on purpose" } };
  const third = await job(await sdk.uploadCalibration({ client: admin, body: zip, query: again }));
  assert.equal(third.version, 3, JSON.stringify(third));
  const noReason = await sdk.uploadCalibration({ client: admin, body: zip, query: { overrides: { force: true } } });
  assert.match(problem(noReason, 422).detail, /force needs a reason/);
  calls.push("upload_calibration_overrides");

  problem(await sdk.getCalibration({ client: admin, path: { version: 999 } }), 404);
  const huge = new Uint8Array(fixture.max_request_bytes).fill(0xff);
  problem(await sdk.predictForm({ client: anyone, body: form(huge) }), 413);
  const gif = new TextEncoder().encode("GIF89a not a picture");
  problem(await sdk.predictPngForm({ client: anyone, body: form(gif, "image/gif") }), 415);
  const invalid = problem(await sdk.predict({ client: anyone, body: asJson(first, { epsilon: 2 }) }), 422);
  assert.ok(invalid.errors?.length);
  const unknown = asJson(first, { instances: [{ object: "no-such-object" as never, bbox: [1, 1, 5, 5] }] });
  problem(await sdk.predict({ client: anyone, body: unknown }), 422);
  report("@hey-api/openapi-ts", calls);
}

main().catch((error) => {
  console.error(error);
  process.exit(1);
});
