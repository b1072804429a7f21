// Open a page in headless Chromium (Debian's, through playwright-core) and follow steps given as JSON:
//   node screenshots.mjs URL STEPS_JSON   with STEPS_JSON = [["wait", ms], ["shot", path], ["click", button text],
//   ["check", checkbox label], ["text", text to wait for], ...]
// Prints one JSON line: the page's console errors and the WebGL renderer it reported.
import { chromium } from "playwright-core";

const [url, stepsJson] = process.argv.slice(2);
const steps = JSON.parse(stepsJson);
const browser = await chromium.launch({
  executablePath: process.env.CHROMIUM ?? "/usr/bin/chromium",
  headless: true,
  // As root: no sandbox; software WebGL (SwiftShader) since there is no GPU; nothing fetched from outside.
  args: ["--no-sandbox", "--disable-gpu", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
    "--disable-quic", "--no-first-run", "--disable-background-networking", "--disable-component-update",
    "--disable-sync"],
});
const errors = [];
let webgl = "";
try {
  const page = await browser.newPage({ viewport: { width: 1280, height: 720 } });
  page.on("console", (m) => {
    const text = m.text();
    if (m.type() === "error") errors.push(text.slice(0, 300));
    if (text.startsWith("WebGL support")) webgl = text.slice(0, 300);
  });
  page.on("pageerror", (e) => errors.push(String(e).slice(0, 300)));
  await page.goto(url, { waitUntil: "load", timeout: 60000 });
  for (const [kind, arg] of steps) {
    if (kind === "wait") await page.waitForTimeout(arg);
    else if (kind === "shot") await page.screenshot({ path: arg });
    else if (kind === "click") await page.getByRole("button", { name: arg, exact: true }).click();
    else if (kind === "check") await page.getByLabel(arg, { exact: true }).check();
    else if (kind === "text") await page.getByText(arg).first().waitFor({ timeout: 60000 });
    else throw new Error(`unknown step ${kind}`);
  }
} finally {
  await browser.close();
}
console.log(JSON.stringify({ errors, webgl }));
