// Reads the JSON a dtx command prints (--json) on stdin with JSON.parse and lists every
// undefined figure: a null whose reason sits beside it under "<name>_undefined"
// (msgs/strict_json.py). One JSON line out: [{"path": "...", "reason": "..."}, ...].
let text = "";
process.stdin.setEncoding("utf8");
process.stdin.on("data", (chunk) => { text += chunk; });
process.stdin.on("end", () => {
  const found = [];
  const walk = (value, path) => {
    if (Array.isArray(value)) {
      value.forEach((item, index) => walk(item, `${path}[${index}]`));
    } else if (value !== null && typeof value === "object") {
      for (const [key, item] of Object.entries(value)) {
        const reason = value[`${key}_undefined`];
        if (item === null && typeof reason === "string") found.push({ path: `${path}.${key}`, reason });
        else walk(item, `${path}.${key}`);
      }
    }
  };
  walk(JSON.parse(text), "$");
  console.log(JSON.stringify(found));
});
