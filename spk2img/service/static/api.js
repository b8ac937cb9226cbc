// The API reference: reads the service's own openapi.json and lists every operation with its
// parameters and answers. Plain DOM nodes and textContent (nothing parsed as HTML, nothing
// fetched from elsewhere), so it passes the service's Content-Security-Policy and works offline.
"use strict";
(function () {
  const main = document.getElementById("api");

  function el(tag, text, cls) {
    const node = document.createElement(tag);
    if (text !== undefined) node.textContent = text;
    if (cls) node.className = cls;
    return node;
  }

  function schemaText(schema, spec) {
    if (!schema) return "";
    if (schema.$ref) return schema.$ref.split("/").pop();
    if (schema.anyOf) return schema.anyOf.map((s) => schemaText(s, spec)).join(" | ");
    if (schema.enum) return schema.enum.join(" | ");
    const range = [];
    if (schema.minimum !== undefined) range.push(`≥ ${schema.minimum}`);
    if (schema.maximum !== undefined) range.push(`≤ ${schema.maximum}`);
    return [schema.type || "", ...range].join(" ").trim();
  }

  function table(headers, rows) {
    const t = el("table");
    const head = el("tr");
    headers.forEach((h) => head.appendChild(el("th", h)));
    t.appendChild(head);
    rows.forEach((row) => {
      const tr = el("tr");
      row.forEach((cell) => tr.appendChild(el("td", cell)));
      t.appendChild(tr);
    });
    return t;
  }

  function operation(path, verb, op, spec) {
    const section = el("section");
    const title = el("h2");
    title.appendChild(el("span", verb.toUpperCase(), "verb"));
    title.appendChild(document.createTextNode(path));
    section.appendChild(title);
    if (op.summary) section.appendChild(el("p", op.summary));
    if (op.description) section.appendChild(el("p", op.description, "muted"));
    const params = op.parameters || [];
    if (params.length) {
      section.appendChild(table(["parameter", "type", "default", "description"], params.map((p) => [
        `${p.name}${p.required ? " *" : ""}`,
        schemaText(p.schema, spec),
        p.schema && p.schema.default !== undefined ? String(p.schema.default) : "",
        p.description || (p.schema && p.schema.description) || "",
      ])));
    }
    if (op.requestBody) {
      const types = Object.keys(op.requestBody.content || {}).join(", ");
      section.appendChild(el("p", `body (${types}): ${op.requestBody.description || ""}`));
    }
    const answers = Object.entries(op.responses || {});
    section.appendChild(table(["status", "answer"], answers.map(([status, r]) => [
      status, `${r.description || ""} (${Object.keys(r.content || {}).join(", ") || "no body"})`,
    ])));
    return section;
  }

  fetch("openapi.json")
    .then((answer) => {
      if (!answer.ok) throw new Error(`openapi.json: HTTP ${answer.status}`);
      return answer.json();
    })
    .then((spec) => {
      document.getElementById("api-version").textContent =
        `${spec.info.title} ${spec.info.version} · OpenAPI ${spec.openapi}`;
      if (spec.info.summary) main.appendChild(el("p", spec.info.summary));
      Object.entries(spec.paths).forEach(([path, verbs]) => {
        Object.entries(verbs).forEach(([verb, op]) => main.appendChild(operation(path, verb, op, spec)));
      });
    })
    .catch((error) => main.appendChild(el("p", String(error), "error")));
})();
