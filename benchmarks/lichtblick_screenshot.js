// A run.mcap as Lichtblick (the open-source fork of Foxglove Studio) shows it with the run's
// foxglove-layout.json, headless: the picture in docs/run-format.md ("The layout").
//
// It serves a built Lichtblick web app and the recording on 127.0.0.1, opens the recording in
// the app over HTTP (`?ds=remote-file`), imports the layout through the app's own "Import from
// file..." (the browser's file picker handed the file a user would pick), seeks to --t seconds of
// the run and takes a screenshot. Nothing here is a test; it documents what a viewer draws.
//
// Lichtblick is not on a package registry as an app: build it from its source (GitHub,
// lichtblick-suite/lichtblick, 1.10.8 here) with its packages from the npm registry. Its yarn
// plugins and fonts are Git LFS files: drop the `plugins:` of .yarnrc.yml (not needed to build)
// and put Inter and IBM Plex Mono woff2 files (npm: @fontsource/inter, @fontsource/ibm-plex-mono)
// in packages/suite-base/src/styles/assets under the names there. Then, in its checkout:
//   corepack enable
//   COREPACK_NPM_REGISTRY=https://registry.npmjs.org yarn install   (.yarnrc.yml: npmRegistryServer the same)
//   yarn web:build:prod                                             (about 70 s here)
//   apt-get install chromium
//   NODE_PATH=$PWD/node_modules node SWARMLOC/benchmarks/lichtblick_screenshot.js web/.webpack \
//       RUN/run.mcap RUN/foxglove-layout.json 25 out.png
// (arguments: the built app, the recording, the layout, seconds into the run, the picture).

const fs = require("fs");
const http = require("http");
const path = require("path");

const handler = require("serve-handler");
const { McapIndexedReader } = require("@mcap/core");
const { chromium } = require("playwright");

async function startTime(file) {
  const fd = await fs.promises.open(file, "r");
  const readable = {
    size: async () => BigInt((await fd.stat()).size),
    read: async (offset, length) => {
      const buf = Buffer.alloc(Number(length));
      await fd.read(buf, 0, Number(length), Number(offset));
      return new Uint8Array(buf);
    },
  };
  const reader = await McapIndexedReader.Initialize({ readable });
  await fd.close();
  return reader.statistics.messageStartTime; // ns, bigint: the run's start (docs/run-format.md, "Times")
}

(async () => {
  const [app, mcap, layoutFile, seconds, out] = process.argv.slice(2);
  const start = await startTime(mcap);
  const at = new Date(Number(start / 1000000n) + Number(seconds) * 1000).toISOString();
  const server = http.createServer((req, res) => {
    if (req.url.startsWith("/run.mcap")) {
      return handler(req, res, { public: path.dirname(path.resolve(mcap)), rewrites: [{ source: "/run.mcap", destination: "/" + path.basename(mcap) }] });
    }
    return handler(req, res, { public: path.resolve(app) });
  });
  await new Promise((ok) => server.listen(0, "127.0.0.1", ok));
  const base = `http://127.0.0.1:${server.address().port}`;
  const layout = fs.readFileSync(layoutFile, "utf8");
  const browser = await chromium.launch({ executablePath: "/usr/bin/chromium",
    args: ["--no-sandbox", "--use-gl=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"] });
  const page = await browser.newPage({ viewport: { width: 1600, height: 1000 } });
  await page.addInitScript((text) => {
    window.showOpenFilePicker = async () => [{ kind: "file", name: "foxglove-layout.json",
      getFile: async () => new File([text], "foxglove-layout.json", { type: "application/json" }) }];
  }, layout);
  await page.goto(`${base}/?ds=remote-file&ds.url=${encodeURIComponent(base + "/run.mcap")}&time=${at}`);
  await page.waitForTimeout(6000);
  await page.getByText("Layouts", { exact: true }).click();
  await page.getByText("Import from file…", { exact: true }).click();
  await page.waitForTimeout(6000);
  await page.screenshot({ path: out });
  await browser.close();
  server.close();
  console.log(`${out}: ${mcap} at ${seconds} s (${at}) with ${layoutFile}`);
})();
