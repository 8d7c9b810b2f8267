// What both pages share: the token from the page's own URL, carried on every request the page
// makes (beyond localhost the server refuses any request without it), and element lookup.
"use strict";
const token = new URLSearchParams(location.search).get("token");
const q = (extra) => { const p = new URLSearchParams(extra || {}); if (token) p.set("token", token); return "?" + p; };
const $ = (id) => document.getElementById(id);
