// The user guide page: docs/*.md as the server ships them (api/v1/page/docs), rendered by markdown.js.
"use strict";

async function showDoc(name) {
  const main = document.getElementById("guide");
  try {
    const response = await fetch(`api/v1/page/docs/${encodeURIComponent(name)}`);
    if (!response.ok) throw new Error(`the server answered ${response.status}`);
    main.innerHTML = renderMarkdown(await response.text());
    document.title = `nlpsf — ${main.querySelector("h1") ? main.querySelector("h1").textContent : name}`;
    document.body.dataset.ready = "true";
  } catch (error) {
    main.innerHTML = "";
    const p = document.createElement("p");
    p.className = "error";
    p.textContent = `The guide could not be loaded: ${error.message === "Failed to fetch" ? "the server cannot be reached" : error.message}.`;
    main.appendChild(p);
    document.body.dataset.ready = "error";
  }
}

document.addEventListener("DOMContentLoaded", async () => {
  const name = new URLSearchParams(location.search).get("page") || "guide";
  try {
    const index = await (await fetch("api/v1/page/docs")).json();
    document.getElementById("doc-pages").innerHTML = index.pages
      .map((p) => `<a href="guide.html?page=${encodeURIComponent(p)}"${p === name ? ' aria-current="page"' : ""}>${p}</a>`)
      .join(" · ");
  } catch (_) {
    // the page list is a convenience; the guide itself says if the server is down
  }
  showDoc(name);
});
