// Mounts the Foxglove app with in-memory storage and the live_view layout.
(async function main() {
  const studio = window;  // the bundle put its exports on window
  const layoutId = "vgm-live-view";

  class MemoryAppConfiguration {
    constructor(values) { this.values = { ...values }; this.listeners = new Map(); }
    get(key) { return this.values[key]; }
    async set(key, value) {
      this.values[key] = value;
      for (const listener of this.listeners.get(key) ?? []) { listener(value); }
    }
    addChangeListener(key, cb) {
      if (!this.listeners.has(key)) { this.listeners.set(key, new Set()); }
      this.listeners.get(key).add(cb);
    }
    removeChangeListener(key, cb) { this.listeners.get(key)?.delete(cb); }
  }

  class MemoryLayoutStorage {
    constructor() { this.layouts = new Map(); }
    key(namespace, id) { return `${namespace}/${id}`; }
    async list(namespace) {
      return [...this.layouts.entries()].filter(([k]) => k.startsWith(`${namespace}/`))
        .map(([, v]) => v);
    }
    async get(namespace, id) { return this.layouts.get(this.key(namespace, id)); }
    async put(namespace, layout) { this.layouts.set(this.key(namespace, layout.id), layout); return layout; }
    async delete(namespace, id) { this.layouts.delete(this.key(namespace, id)); }
    async importLayouts() {}
    async migrateUnnamespacedLayouts() {}
  }

  const layoutData = await (await fetch("/layout.json")).json();
  const layoutStorage = new MemoryLayoutStorage();
  // The app keeps local layouts in the "local" namespace.
  await layoutStorage.put("local", {
    id: layoutId, name: "vgm live_view", permission: "CREATOR_WRITE",
    baseline: { data: layoutData, savedAt: new Date().toISOString() },
    working: undefined, syncInfo: undefined,
  });
  const appConfiguration = new MemoryAppConfiguration({});
  studio.overwriteFetch();
  await studio.initI18n();
  const dataSources = [
    new studio.FoxgloveWebSocketDataSourceFactory(),
    new studio.RemoteDataSourceFactory(),
    new studio.McapLocalDataSourceFactory(),
  ];
  const app = React.createElement(studio.App, {
    deepLinks: [window.location.href],
    dataSources,
    appConfiguration,
    layoutStorage,
    extensionLoaders: [],
    enableGlobalCss: true,
  });
  ReactDOM.render(app, document.getElementById("root"));
  window.vgmHostReady = true;
})().catch((error) => {
  window.vgmHostError = String(error && error.stack || error);
  console.error(error);
});
