/* georeg map view: builds the Leaflet map of results/report/map.html from the embedded JSON.
 * Layers are in full-resolution map pixel coordinates (col, row; rows down), drawn in
 * L.CRS.Simple as (lat, lng) = (-row, col). Nothing is loaded from the network. */
(function () {
  "use strict";

  var data = JSON.parse(document.getElementById("map-data").textContent);
  var T = data.crs.transform; // a, b, c, d, e, f: map x = a col + b row + c, y = d col + e row + f

  function ll(c, r) { return L.latLng(-r, c); }
  function box(b) { return L.latLngBounds(ll(b[0], b[3]), ll(b[2], b[1])); }
  function esc(s) {
    return String(s).replace(/[&<>"']/g, function (ch) {
      return {"&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;"}[ch];
    });
  }
  var BAD = {false_accept: 1, missed: 1};
  function statusClass(status, outcome) {
    if (BAD[outcome]) return "bad";
    return status === "registered" ? "ok" : "na";
  }

  var map = L.map("map", {
    crs: L.CRS.Simple, minZoom: -10, maxZoom: 5, zoomSnap: 0.25, zoomDelta: 0.5,
    wheelPxPerZoomLevel: 90, attributionControl: true
  });
  map.attributionControl.setPrefix("Leaflet " + L.version + " (bundled)");
  map.createPane("orthoPane").style.zIndex = 250;
  map.createPane("queryPane").style.zIndex = 300;

  var full = box(data.ortho.bounds);
  var ortho = L.imageOverlay(data.ortho.src, full, {pane: "orthoPane", attribution: "map " +
    data.size[0] + " x " + data.size[1] + " px, " + esc(data.crs.name)});
  ortho.on("load", function () { document.body.setAttribute("data-ortho", "loaded"); });
  ortho.on("error", function () { document.body.setAttribute("data-ortho", "error"); });
  ortho.addTo(map);

  // ------------------------------------------------------------------ groups and styles
  var groups = {
    queries: L.layerGroup(), footprints: L.layerGroup(), truth: L.layerGroup(),
    cameras: L.layerGroup(), looks: L.layerGroup(), trajectories: L.layerGroup()
  };
  var LABELS = {
    queries: "query images", footprints: "query footprints", truth: "truth (dashed)",
    cameras: "frame cameras and footprints", looks: "look directions",
    trajectories: "video trajectories"
  };
  var byId = {};

  function styleOf(p) {
    switch (p.kind) {
      case "query_footprint":
        var bad = statusClass(p.status, p.outcome) === "bad";
        return {color: bad ? "#ff2d55" : "#00e000", weight: 2.5, fill: true, fillOpacity: 0.06};
      case "query_truth":
        return {color: "#ff3df5", weight: 2, dashArray: "6 5", fill: false};
      case "frame_footprint":
        return {color: "#19d3f3", weight: 1.6, fill: true, fillOpacity: 0.08};
      case "look":
        return p.video ? {color: "#ffd400", weight: 1.3, opacity: 0.75} :
          {color: "#ffd400", weight: 2.2, opacity: 0.95};
      case "path":
        return {color: "#19d3f3", weight: 3.5, opacity: 0.95};
      case "truth_path":
        return {color: "#ff3df5", weight: 2, dashArray: "6 5", opacity: 0.9};
      default:
        return {}; // points: styled by pointLayer
    }
  }

  function infoTable(p) {
    var rows = (p.info || []).map(function (r) {
      return "<tr><th>" + esc(r[0]) + "</th><td>" + esc(r[1]) + "</td></tr>";
    }).join("");
    var anchor = p.kind && p.kind.indexOf("query") === 0 ? "#q-" + p.name : "#frames";
    return '<div class="info"><table>' + rows + '</table><a href="' + esc(data.report + anchor) +
      '">details in the report</a></div>';
  }

  function pointLayer(f, latlng) {
    var p = f.properties;
    if (p.kind === "truth_camera") {
      return L.circleMarker(latlng, {radius: 6, color: "#ff3df5", weight: 2, dashArray: "3 3",
        fill: true, fillOpacity: 0.05, className: "georeg-truth_camera"});
    }
    var r = p.video ? (p.keyframe ? 4.5 : 3.2) : 7;
    var bad = p.status !== "registered";
    return L.circleMarker(latlng, {radius: r, color: "#111", weight: 1.5,
      fillColor: bad ? "#ff2d55" : (p.keyframe ? "#ffffff" : "#ff9f1c"), fillOpacity: 1,
      className: "georeg-camera"});
  }

  var geo = L.geoJSON(data.features, {
    coordsToLatLng: function (c) { return ll(c[0], c[1]); },
    style: function (f) {
      var st = styleOf(f.properties);
      if (st.color) st.className = "georeg-" + f.properties.kind;
      return st;
    },
    pointToLayer: pointLayer,
    onEachFeature: function (f, layer) {
      var p = f.properties;
      layer.bindPopup(infoTable(p), {maxWidth: 420});
      layer.bindTooltip(esc(p.name) + " (" + esc(p.status) + ")", {sticky: true});
      groups[p.layer].addLayer(layer);
      if (!byId[p.id] || p.kind === "query_footprint" || p.kind === "camera" || p.kind === "path") {
        byId[p.id] = layer;
      }
    }
  });

  var overlays = [];
  data.queries.forEach(function (q) {
    if (!q.overlay) return;
    var o = L.imageOverlay(q.overlay.src, box(q.overlay.bounds), {pane: "queryPane",
      interactive: false, className: "georeg-query-image"});
    o.on("error", function () { document.body.setAttribute("data-query-image", "error"); });
    overlays.push(o);
    groups.queries.addLayer(o);
    if (!byId[q.id]) byId[q.id] = o;
  });

  // path, footprints and cameras above the images; truth dashed on top
  ["queries", "footprints", "trajectories", "looks", "cameras", "truth"].forEach(function (k) {
    groups[k].addTo(map);
  });
  map.fitBounds(full, {padding: [10, 10]});

  var baseLayers = {"orthophoto": ortho, "no orthophoto": L.layerGroup()};
  var overlayLayers = {};
  Object.keys(LABELS).forEach(function (k) {
    if (groups[k].getLayers().length) overlayLayers[LABELS[k]] = groups[k];
  });
  L.control.layers(baseLayers, overlayLayers, {collapsed: false, position: "topright"}).addTo(map);

  // ------------------------------------------------------------------ mouse position
  var Pos = L.Control.extend({
    options: {position: "bottomleft"},
    onAdd: function () {
      var div = L.DomUtil.create("div", "georeg-pos");
      div.textContent = "map CRS: " + data.crs.name + " (move the mouse over the map)";
      return div;
    }
  });
  var pos = new Pos().addTo(map);
  map.on("mousemove", function (e) {
    var c = e.latlng.lng, r = -e.latlng.lat;
    var x = T[0] * c + T[1] * r + T[2], y = T[3] * c + T[4] * r + T[5];
    pos.getContainer().textContent = "x " + x.toFixed(2) + "  y " + y.toFixed(2) + "  (" +
      data.crs.name + ")   map px " + c.toFixed(1) + ", " + r.toFixed(1);
  });

  // ------------------------------------------------------------------ query image: opacity / swipe
  var side = document.getElementById("side");
  var mode = "opacity";
  var swipeLine = L.DomUtil.create("div", "georeg-swipe", map.getContainer());
  var queryPane = map.getPane("queryPane");
  var slider;

  function applyQueryView() {
    var v = slider ? slider.value / 100 : 0.8;
    if (mode === "opacity") {
      queryPane.style.clip = "";
      swipeLine.style.display = "none";
      overlays.forEach(function (o) { o.setOpacity(v); });
    } else {
      overlays.forEach(function (o) { o.setOpacity(1); });
      var size = map.getSize();
      var nw = map.containerPointToLayerPoint([0, 0]);
      var se = map.containerPointToLayerPoint(size);
      var x = Math.round(size.x * v);
      queryPane.style.clip = "rect(" + nw.y + "px, " + (nw.x + x) + "px, " + se.y + "px, " + nw.x + "px)";
      swipeLine.style.display = map.hasLayer(groups.queries) ? "block" : "none";
      swipeLine.style.left = x + "px";
    }
  }
  map.on("move zoom resize overlayadd overlayremove", applyQueryView);

  function section(title) {
    var s = L.DomUtil.create("section", "", side);
    L.DomUtil.create("h2", "", s).textContent = title;
    return s;
  }

  if (overlays.length) {
    var s = section("query image over the map");
    s.innerHTML += '<div class="modes"><label><input type="radio" name="qmode" value="opacity" checked> opacity</label>' +
      '<label><input type="radio" name="qmode" value="swipe"> swipe</label></div>' +
      '<input type="range" id="query-slider" min="0" max="100" value="80">' +
      '<p class="note">opacity: the query band (blue-grey) over the orthophoto; swipe: the query left of the line, the orthophoto right of it.</p>';
    slider = document.getElementById("query-slider");
    slider.addEventListener("input", applyQueryView);
    Array.prototype.forEach.call(s.querySelectorAll("input[name=qmode]"), function (r) {
      r.addEventListener("change", function () { mode = r.value; applyQueryView(); });
    });
  }
  applyQueryView();

  // ------------------------------------------------------------------ lists
  function focus(id) {
    var layer = byId[id];
    if (!layer) return;
    if (layer.getBounds) map.fitBounds(layer.getBounds(), {padding: [60, 60], maxZoom: 1, animate: false});
    else if (layer.getLatLng) map.setView(layer.getLatLng(), Math.max(map.getZoom(), 0), {animate: false});
    if (layer.openPopup) layer.openPopup();
  }

  function item(list, id, label, cls, detail) {
    var li = L.DomUtil.create("li", "", list);
    li.innerHTML = '<span class="dot ' + cls + '"></span><a href="#" data-id="' + esc(id) + '">' +
      esc(label) + "</a> <span class=\"" + cls + '">' + esc(detail) + "</span>";
    li.querySelector("a").addEventListener("click", function (ev) {
      ev.preventDefault();
      focus(id);
    });
  }

  var nReg = 0;
  if (data.queries.length) {
    var ul = L.DomUtil.create("ul", "", section("queries"));
    data.queries.forEach(function (q) {
      if (q.status === "registered") nReg += 1;
      var cls = statusClass(q.status, q.outcome);
      var detail = q.status + (q.outcome !== "no_truth" ? ", " + q.outcome.replace(/_/g, " ") : "");
      item(ul, q.id, q.name, cls, detail);
    });
  }
  data.sets.forEach(function (st) {
    var ul = L.DomUtil.create("ul", "", section((st.kind === "video" ? "video " : "frames ") + st.name));
    var cls = st.registered ? "ok" : "bad";
    item(ul, st.id, st.kind === "video" ? "trajectory" : "all frames", cls,
      st.registered + " of " + st.entries + " registered");
    st.frames.forEach(function (f) {
      item(ul, f.id, f.name, f.status === "registered" ? "ok" : "bad", f.status.replace(/_/g, " "));
    });
  });
  byIdSets();
  function byIdSets() {
    data.sets.forEach(function (st) {
      if (byId[st.id]) return;
      var g = L.featureGroup(groups.cameras.getLayers().filter(function (l) {
        return l.feature && l.feature.properties.set === st.name;
      }));
      if (g.getLayers().length) byId[st.id] = {getBounds: function () { return g.getBounds(); }};
    });
  }

  var legend = L.DomUtil.create("div", "", section("legend"));
  legend.innerHTML =
    '<ul class="legend">' +
    '<li><i class="sw" style="border-color:#00e000"></i>query footprint (registered)</li>' +
    '<li><i class="sw" style="border-color:#ff2d55"></i>query footprint (wrong place)</li>' +
    '<li><i class="sw dash" style="border-color:#ff3df5"></i>truth: footprint, camera, path</li>' +
    '<li><i class="pt" style="background:#ff9f1c"></i>frame camera (click: status, errors)</li>' +
    '<li><i class="sw" style="border-color:#19d3f3"></i>frame footprint, video path</li>' +
    '<li><i class="ln" style="background:#ffd400"></i>look direction</li>' +
    "</ul>";

  document.getElementById("verdict").textContent = data.queries.length ?
    nReg + " of " + data.queries.length + " queries registered" : "";

  window.georegMap = {map: map, groups: groups, overlays: overlays, byId: byId, focus: focus};
  document.body.setAttribute("data-ready", "1");
})();
