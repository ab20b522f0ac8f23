// Types generated untouched by openapi-typescript, calls made with openapi-fetch (the pair's usual
// use), driven through predict (JSON and form), the drawing, batches, uploads (raw and form), jobs,
// activation, an audit, and typed errors, each parsed as the document's Problem. The forms send
// their JSON parts as Blobs of type application/json (with a filename, as FormData gives them), and
// the raw zip goes with whatever Content-Type openapi-fetch sets: both as browsers and Node send them.
import assert from "node:assert/strict";
import createClient from "openapi-fetch";
import type { components, paths } from "./generated/schema";
import { base64, blob, bytes, finished, fixture, problem, report } from "./common";

type Schemas = components["schemas"];
type Job = Schemas["JobOut"];
type Parameters = Schemas["PredictParameters"];
type Binary = string; // openapi-typescript's type for format: binary; a Blob is sent in its place

const anyone = createClient<paths>({ baseUrl: fixture.url });
// The upload's overrides (force, allow_duplicate, reason) are an exploded form-style query object,
// as the document says; openapi-fetch's default for objects is deepObject, so the style is named here.
const admin = createClient<paths>({
  baseUrl: fixture.url,
  headers: { Authorization: `Bearer ${fixture.token}` },
  querySerializer: { object: { style: "form", explode: true } },
});
const stranger = createClient<paths>({ baseUrl: fixture.url, headers: { Authorization: "Bearer not-the-token" } });
const calls: string[] = [];

const [first, ...others] = fixture.images;
const instances = (image: (typeof fixture.images)[0]) => image.instances as Parameters["instances"];
const asJson = (image: (typeof fixture.images)[0], options: Partial<Schemas["PredictJson"]> = {}) => ({
  image_base64: base64(image.path),
  instances: instances(image),
  ...options,
});
const file = (data: Uint8Array<ArrayBuffer>, type: string) => blob(data, type) as unknown as Binary;
/** multipart/form-data with every JSON part as a Blob of type application/json (it gets a filename). */
function formData(body: object): FormData {
  const form = new FormData();
  for (const [name, value] of Object.entries(body)) {
    if (value instanceof Blob) form.append(name, value, `${name}.bin`);
    else form.append(name, new Blob([JSON.stringify(value)], { type: "application/json" }));
  }
  return form;
}
const asForm = { bodySerializer: formData };
const raw = { bodySerializer: (body: Binary) => body as unknown as Blob };
const form = (image: Uint8Array<ArrayBuffer>, type = "image/jpeg") => ({
  image: file(image, type),
  request: { instances: instances(first) },
});

async function job(answer: { data?: Job; error?: unknown; response: Response }): Promise<Job> {
  assert.equal(answer.response.status, 202, JSON.stringify(answer.error));
  const get = async (id: string) =>
    (await admin.GET("/v1/admin/jobs/{job_id}", { params: { path: { job_id: id } } })).data as Job;
  return (await finished(answer.data as Job, get)) as Job;
}

async function main(): Promise<void> {
  const model = await anyone.GET("/v1/model");
  assert.ok(model.data?.manifest.keypoints.length, "model info");
  calls.push("model_info");

  problem(await anyone.POST("/v1/predict", { body: asJson(first) }), 503); // none active yet
  problem(await stranger.GET("/v1/admin/calibrations"), 401);

  const zip = file(bytes(fixture.whole_zip), "application/zip");
  const upload = await admin.POST("/v1/admin/calibrations", { body: zip, params: { query: { name: "first" } }, ...raw });
  const made = await job(upload);
  assert.equal(made.state, "succeeded", JSON.stringify(made));
  assert.equal(made.version, 1);
  calls.push("upload_calibration", "get_job");
  const activate = "/v1/admin/calibrations/{version}/activate";
  const one = { path: { version: 1 } };
  const refused = problem(await admin.POST(activate, { params: one, body: {} }), 409);
  assert.match(refused.detail, /CKS_MIN_CALIBRATION_INSTANCES/);
  const forced = { force: true, reason: "TypeScript client test: the samples are below the floor" };
  assert.equal((await admin.POST(activate, { params: one, body: forced })).data?.version, 1);
  calls.push("activate_calibration");

  const answer = await anyone.POST("/v1/predict", { body: asJson(first) });
  assert.equal(answer.data?.instances.length, first.instances.length, JSON.stringify(answer.error));
  const viaForm = await anyone.POST("/v1/predict/form", { body: form(bytes(first.path)), ...asForm });
  assert.deepEqual(viaForm.data, answer.data);
  calls.push("predict", "predict_form");
  const drawing = await anyone.POST("/v1/predict/png", { body: asJson(first), parseAs: "blob" });
  const png = new Uint8Array(await (drawing.data as unknown as Blob).arrayBuffer());
  assert.deepEqual([...png.slice(0, 8)], [0x89, 0x50, 0x4e, 0x47, 0x0d, 0x0a, 0x1a, 0x0a]);
  const drawnForm = await anyone.POST("/v1/predict/png/form", {
    body: form(bytes(first.path)),
    parseAs: "blob",
    ...asForm,
  });
  assert.equal((drawnForm.data as unknown as Blob).size, png.length);
  calls.push("predict_png", "predict_png_form");

  const items = [first, ...others].slice(0, 3).map((image) => asJson(image));
  const batch = await anyone.POST("/v1/predict/batch", { body: { items } });
  assert.deepEqual(batch.data?.items.map((item) => item.status), [200, 200, 200]);
  assert.deepEqual(batch.data?.items[0].result, answer.data);
  const parts = { image_0: file(bytes(first.path), "image/jpeg"), request_0: { instances: instances(first) } };
  const formBatch = await anyone.POST("/v1/predict/batch/form", { body: parts, ...asForm });
  assert.deepEqual(formBatch.data?.items[0].result, answer.data);
  calls.push("predict_batch", "predict_batch_form");

  const part = { file: file(bytes(fixture.part_zip), "application/zip") };
  const query = { query: { name: "part" } };
  const second = await job(await admin.POST("/v1/admin/forms/calibrations", { body: part, params: query, ...asForm }));
  assert.equal(second.version, 2, JSON.stringify(second));
  calls.push("upload_calibration_form");
  const two = { path: { version: 2 } };
  const comparison = await admin.GET("/v1/admin/calibrations/{version}/compare", { params: two });
  assert.equal(comparison.data?.allowed, false);
  await admin.POST(activate, { params: two, body: forced });
  const rollback = { force: true, reason: "roll back to the whole batch" };
  assert.equal((await admin.POST(activate, { params: one, body: rollback })).data?.version, 1);
  assert.equal((await admin.GET("/v1/admin/calibrations/{version}", { params: one })).data?.active, true);

  const auditQuery = { query: { version: 2, dedupe: true } };
  const audited = await job(await admin.POST("/v1/admin/audits", { body: zip, params: auditQuery, ...raw }));
  assert.equal(audited.state, "succeeded", JSON.stringify(audited));
  const auditId = { path: { audit_id: audited.result?.audit as number } };
  assert.equal((await admin.GET("/v1/admin/audits/{audit_id}", { params: auditId })).data?.version, 2);
  calls.push("start_audit", "get_audit");

  const again = { query: { overrides: { allow_duplicate: true, reason: "the same batch again, on purpose" } } };
  const third = await job(await admin.POST("/v1/admin/calibrations", { body: zip, params: again, ...raw }));
  assert.equal(third.version, 3, JSON.stringify(third));
  const noReason = { query: { overrides: { force: true } } };
  const refusedForce = await admin.POST("/v1/admin/calibrations", { body: zip, params: noReason, ...raw });
  assert.match(problem(refusedForce, 422).detail, /force needs a reason/);
  calls.push("upload_calibration_overrides");

  problem(await admin.GET("/v1/admin/calibrations/{version}", { params: { path: { version: 999 } } }), 404);
  const huge = new Uint8Array(fixture.max_request_bytes).fill(0xff);
  problem(await anyone.POST("/v1/predict/form", { body: form(huge), ...asForm }), 413);
  const gif = new TextEncoder().encode("GIF89a not a picture");
  problem(await anyone.POST("/v1/predict/png/form", { body: form(gif, "image/gif"), ...asForm }), 415);
  const invalid = problem(await anyone.POST("/v1/predict", { body: asJson(first, { epsilon: 2 }) }), 422);
  assert.ok(invalid.errors?.length);
  const unknown = asJson(first, { instances: [{ object: "no-such-object" as never, bbox: [1, 1, 5, 5] }] });
  problem(await anyone.POST("/v1/predict", { body: unknown }), 422);
  report("openapi-typescript + openapi-fetch", calls);
}

main().catch((error) => {
  console.error(error);
  process.exit(1);
});
