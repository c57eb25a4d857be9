// Compare page: each inspection's plate map; zooming or panning one moves the other to the same view.
import { PlateMap } from "./plate_map.js";

const maps = [...document.querySelectorAll(".plate-map")].map((figure) => new PlateMap(figure));

Promise.all(maps.map((map) => map.load())).then(() => {
  for (const map of maps) {
    map.onView = (view) => {
      for (const other of maps) if (other !== map) other.follow(view);
    };
  }
}).catch((err) => {
  for (const map of maps) map.readout.textContent = `The map could not be drawn: ${err.message}`;
});
