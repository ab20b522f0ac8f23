// A client generated untouched by openapi-generator's typescript-axios (its API classes over axios),
// driven through predict (JSON and form), the drawing, batches (JSON and form), frames (whole, and as
// two regions of two encodings: an array of pixels parts), uploads (raw and form), jobs, activation,
// an audit, and typed errors, each parsed as the document's Problem. This generator reads anyOf and
// multipart encodings literally: a part typed `any` or a list of content types would break these calls.
import assert from "node:assert/strict";
import { readFileSync } from "node:fs";
import { isAxiosError } from "axios";
import { AdminApi, Configuration, ModelApi, PredictionApi } from "./generated/axios";
import type { JobOut, PredictJson, PredictParameters } from "./generated/axios";
import { base64, bytes, finished, fixture, problem, report } from "./common";
import type { ProblemLike } from "./common";

const basePath = fixture.url;
const anyone = new PredictionApi(new Configuration({ basePath }));
const admin = new AdminApi(new Configuration({ basePath, accessToken: fixture.token }));
const stranger = new AdminApi(new Configuration({ basePath, accessToken: "not-the-token-at-all" }));
const model = new ModelApi(new Configuration({ basePath }));
const calls: string[] = [];

type Image = (typeof fixture.images)[0];
const [first, ...others] = fixture.images;
const instances = (image: Image) => image.instances as PredictParameters["instances"];
const asJson = (image: Image, options: Partial<PredictJson> = {}): PredictJson => ({
  image_base64: base64(image.path),
  instances: instances(image),
  ...options,
});
const file = (data: Uint8Array<ArrayBuffer>, type: string, name = "file.bin") => new File([data], name, { type });
const jpeg = (path: string) => file(bytes(path), "image/jpeg", "image.jpg");
const binary = { responseType: "arraybuffer" as const };

/** The Problem of a call axios rejects: its status, a detail, the request's id in body and header. */
async function refused(call: Promise<unknown>, status: number): Promise<ProblemLike> {
  try {
    await call;
  } catch (error) {
    if (!isAxiosError(error) || error.response === undefined) throw error;
    const headers = new Headers();
    for (const [name, value] of Object.entries(error.response.headers)) {
      if (typeof value === "string") headers.set(name, value);
    }
    const response = new Response(null, { status: error.response.status, headers });
    return problem({ error: error.response.data, response }, status);
  }
  assert.fail(`expected ${status}`);
}

async function job(call: Promise<{ status: number; data: JobOut }>): Promise<JobOut> {
  const answer = await call;
  assert.equal(answer.status, 202);
  return (await finished(answer.data, async (id) => (await admin.getJob(id)).data)) as JobOut;
}

async function frames(expected: unknown): Promise<void> {
  const { frame } = fixture;
  const picture = jpeg(frame.path);
  const asked = { instances: frame.instances as PredictParameters["instances"] };
  const size = { width: frame.width, height: frame.height };
  const whole = await anyone.predictFrame([picture], { ...asked, frame: { ...size, encoding: "jpeg" } });
  assert.deepEqual(whole.data, expected);
  calls.push("predict_frame");
  const { path, encoding, ...region } = frame.region;
  const rest = frame.instances.map((_, i) => i).slice(1);
  const regions = [
    { ...region, encoding: encoding as "bgr8", instances: [0] },
    { x_offset: 0, y_offset: 0, ...size, encoding: "jpeg" as const, instances: rest },
  ];
  const raw = file(new Uint8Array(readFileSync(path)), "application/octet-stream");
  const parts = await anyone.predictFrame([raw, picture], { ...asked, frame: size, regions });
  assert.deepEqual(parts.data, expected);
  calls.push("predict_frame_regions");
}

async function main(): Promise<void> {
  assert.ok((await model.modelInfo()).data.manifest.keypoints.length, "model info");
  calls.push("model_info");

  await refused(anyone.predict(asJson(first)), 503); // none active yet
  await refused(stranger.listCalibrations(), 401);

  const zip = () => file(bytes(fixture.whole_zip), "application/zip", "batch.zip");
  const made = await job(admin.uploadCalibration(zip(), "first"));
  assert.equal(made.state, "succeeded", JSON.stringify(made));
  assert.equal(made.version, 1);
  calls.push("upload_calibration", "get_job");
  const notForced = refused(admin.activateCalibration(1, undefined, {}), 409);
  assert.match((await notForced).detail, /CKS_MIN_CALIBRATION_INSTANCES/);
  const forced = { force: true, reason: "TypeScript client test: the samples are below the floor" };
  assert.equal((await admin.activateCalibration(1, undefined, forced)).data.version, 1);
  calls.push("activate_calibration");

  const answer = await anyone.predict(asJson(first));
  assert.equal(answer.data.instances.length, first.instances.length);
  const viaForm = await anyone.predictForm(jpeg(first.path), { instances: instances(first) });
  assert.deepEqual(viaForm.data, answer.data);
  calls.push("predict", "predict_form");
  const drawing = await anyone.predictPng(asJson(first), undefined, binary);
  const png = new Uint8Array(drawing.data as unknown as ArrayBuffer);
  assert.deepEqual([...png.slice(0, 8)], [0x89, 0x50, 0x4e, 0x47, 0x0d, 0x0a, 0x1a, 0x0a]);
  const drawnForm = await anyone.predictPngForm(jpeg(first.path), { instances: instances(first) }, undefined, binary);
  assert.equal((drawnForm.data as unknown as ArrayBuffer).byteLength, png.length);
  calls.push("predict_png", "predict_png_form");

  const items = [first, ...others].slice(0, 3).map((image) => asJson(image));
  const batch = await anyone.predictBatch({ items });
  assert.deepEqual(batch.data.items.map((item) => item.status), [200, 200, 200]);
  assert.deepEqual(batch.data.items[0].result, answer.data);
  const formBatch = await anyone.predictBatchForm(jpeg(first.path), { instances: instances(first) });
  assert.deepEqual(formBatch.data.items.map((item) => item.status), [200]);
  assert.deepEqual(formBatch.data.items[0].result, answer.data);
  calls.push("predict_batch", "predict_batch_form");
  const framed = fixture.images.find((image) => image.path === fixture.frame.path) as Image;
  await frames((await anyone.predict(asJson(framed))).data);

  const part = file(bytes(fixture.part_zip), "application/zip", "part.zip");
  const second = await job(admin.uploadCalibrationForm(part, "part"));
  assert.equal(second.version, 2, JSON.stringify(second));
  calls.push("upload_calibration_form");
  assert.equal((await admin.compareCalibration(2)).data.allowed, false);
  await admin.activateCalibration(2, undefined, forced);
  const rollback = { force: true, reason: "roll back to the whole batch" };
  assert.equal((await admin.activateCalibration(1, undefined, rollback)).data.version, 1);
  assert.equal((await admin.getCalibration(1)).data.active, true);

  const audited = await job(admin.startAudit(zip(), 2, undefined, undefined, undefined, true));
  assert.equal(audited.state, "succeeded", JSON.stringify(audited));
  assert.equal((await admin.getAudit(audited.result?.audit as number)).data.version, 2);
  calls.push("start_audit", "get_audit");

  const again = { allow_duplicate: true, reason: "the same batch again, on purpose" };
  const upload = (overrides: object) =>
    admin.uploadCalibration(zip(), undefined, undefined, undefined, undefined, undefined, undefined, undefined, overrides);
  const third = await job(upload(again));
  assert.equal(third.version, 3, JSON.stringify(third));
  assert.match((await refused(upload({ force: true }), 422)).detail, /force needs a reason/);
  calls.push("upload_calibration_overrides");

  await refused(admin.getCalibration(999), 404);
  const huge = file(new Uint8Array(fixture.max_request_bytes).fill(0xff), "image/jpeg");
  await refused(anyone.predictForm(huge, { instances: instances(first) }), 413);
  const gif = file(new TextEncoder().encode("GIF89a not a picture"), "image/gif");
  await refused(anyone.predictPngForm(gif, { instances: instances(first) }), 415);
  const invalid = await refused(anyone.predict(asJson(first, { epsilon: 2 })), 422);
  assert.ok(invalid.errors?.length);
  const unknown = asJson(first, { instances: [{ object: "no-such-object" as never, bbox: [1, 1, 5, 5] }] });
  await refused(anyone.predict(unknown), 422);
  report("openapi-generator typescript-axios", calls);
}

main().catch((error) => {
  console.error(error);
  process.exit(1);
});
