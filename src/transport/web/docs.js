// factord API docs: reads /v1/openapi.json (same origin, no network beyond it) and lists the
// operations with their parameters, bodies and responses, then every component schema.
"use strict";

function el(tag, attrs, ...children) {
  const node = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) node.setAttribute(k, v);
  for (const child of children) {
    if (child === null || child === undefined) continue;
    node.append(child instanceof Node ? child : document.createTextNode(String(child)));
  }
  return node;
}

// Descriptions are Markdown: `code` spans become <code>, the rest stays text (no HTML is
// interpreted, so a description cannot inject any).
function prose(text) {
  const span = el("span", {});
  String(text || "").split("`").forEach((part, i) => {
    if (part) span.append(i % 2 ? el("code", {}, part) : document.createTextNode(part));
  });
  return span;
}

function refName(ref) {
  return ref.split("/").pop();
}

// A short type text for a schema: `Batch`, `array of integer`, `string | null`, …
function typeText(schema) {
  if (!schema) return "";
  if (schema.$ref) return refName(schema.$ref);
  for (const key of ["oneOf", "anyOf", "allOf"]) {
    if (schema[key]) return schema[key].map(typeText).join(key === "allOf" ? " & " : " | ");
  }
  if (schema.enum) return schema.enum.map((v) => JSON.stringify(v)).join(" | ");
  const type = Array.isArray(schema.type) ? schema.type.join(" | ") : schema.type || "any";
  if (schema.items) return `${type} of ${typeText(schema.items)}`;
  return type;
}

function linkedType(schema) {
  const text = typeText(schema);
  if (schema && schema.$ref) return el("a", { href: `#schema-${refName(schema.$ref)}`, class: "type" }, text);
  return el("span", { class: "type" }, text);
}

function resolve(api, item) {
  if (item && item.$ref && item.$ref.startsWith("#/components/")) {
    const [, , kind, name] = item.$ref.split("/");
    return (api.components[kind] || {})[name] || item;
  }
  return item;
}

function operation(api, path, method, op) {
  const box = el("div", { class: "op", id: op.operationId || `${method}-${path}` });
  box.append(el("h3", {}, el("span", { class: "method" }, method), path));
  if (op.summary) box.append(el("p", {}, prose(op.summary)));
  if (op.description) box.append(el("p", { class: "muted" }, prose(op.description)));
  const params = op.parameters || [];
  if (params.length) {
    const rows = params.map((p) => el("tr", {}, el("td", {}, el("code", {}, p.name)), el("td", {}, p.in),
      el("td", {}, p.required ? "required" : ""), el("td", {}, linkedType(p.schema)), el("td", {}, prose(p.description))));
    box.append(el("table", {}, el("tr", {}, ...["parameter", "in", "", "type", ""].map((h) => el("th", {}, h))), ...rows));
  }
  if (op.requestBody) {
    const body = op.requestBody;
    const contents = Object.entries(body.content || {});
    box.append(el("p", {}, "Body: ", ...contents.flatMap(([type, c]) => [el("code", {}, type), " ", linkedType(c.schema), " "]),
      body.description ? "— " : "", body.description ? prose(body.description) : null));
  }
  const rows = Object.entries(op.responses || {}).map(([status, response]) => {
    const r = resolve(api, response);
    const contents = Object.entries(r.content || {});
    return el("tr", {}, el("td", {}, el("code", {}, status)),
      el("td", {}, ...contents.flatMap(([type, c]) => [el("code", {}, type), " ", linkedType(c.schema), " "])),
      el("td", {}, prose(r.description)));
  });
  box.append(el("table", {}, el("tr", {}, ...["status", "body", ""].map((h) => el("th", {}, h))), ...rows));
  return box;
}

function schemaBox(name, schema) {
  const box = el("div", { class: "schema", id: `schema-${name}` }, el("h3", {}, name));
  if (schema.description) box.append(el("p", { class: "muted" }, prose(schema.description)));
  const required = new Set(schema.required || []);
  const props = Object.entries(schema.properties || {});
  if (props.length) {
    box.append(el("table", {}, el("tr", {}, ...["field", "", "type", ""].map((h) => el("th", {}, h))),
      ...props.map(([field, s]) => el("tr", {}, el("td", {}, el("code", {}, field)), el("td", {}, required.has(field) ? "required" : ""),
        el("td", {}, linkedType(s)), el("td", {}, prose(s.description))))));
  }
  for (const key of ["oneOf", "anyOf", "allOf"]) {
    if (!schema[key]) continue;
    box.append(el("p", {}, `${key}:`));
    const list = el("ul", {});
    for (const variant of schema[key]) {
      const fields = Object.keys(variant.properties || {});
      list.append(el("li", {}, linkedType(variant), fields.length ? ` {${fields.join(", ")}}` : "",
        variant.description ? " — " : "", variant.description ? prose(variant.description) : null));
    }
    box.append(list);
  }
  if (!props.length && !schema.oneOf && !schema.anyOf && !schema.allOf) box.append(el("p", {}, linkedType(schema)));
  return box;
}

async function main() {
  const status = document.getElementById("status");
  let api;
  try {
    const response = await fetch("/v1/openapi.json", { headers: { Accept: "application/json" } });
    if (!response.ok) throw new Error(`HTTP ${response.status}`);
    api = await response.json();
  } catch (e) {
    status.textContent = `could not read /v1/openapi.json: ${e.message}`;
    status.classList.add("error");
    return;
  }
  status.textContent = `OpenAPI ${api.openapi}, version ${api.info.version}`;
  document.getElementById("title").textContent = api.info.title;
  document.getElementById("description").replaceChildren(prose(api.info.description));
  const operations = document.getElementById("operations");
  const toc = document.getElementById("toc");
  const byTag = new Map();
  for (const [path, item] of Object.entries(api.paths || {})) {
    for (const [method, op] of Object.entries(item)) {
      if (!["get", "put", "post", "delete", "patch"].includes(method)) continue;
      const tag = (op.tags || ["other"])[0];
      if (!byTag.has(tag)) byTag.set(tag, []);
      byTag.get(tag).push(operation(api, path, method, op));
    }
  }
  for (const [tag, boxes] of byTag) {
    toc.append(el("a", { href: `#tag-${tag}` }, tag));
    operations.append(el("h2", { id: `tag-${tag}` }, tag), ...boxes);
  }
  toc.append(el("a", { href: "#schemas" }, "schemas"));
  const schemas = document.getElementById("schemas");
  for (const [name, schema] of Object.entries((api.components || {}).schemas || {})) {
    schemas.append(schemaBox(name, schema));
  }
}

main();
