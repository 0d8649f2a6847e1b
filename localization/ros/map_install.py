"""A map from the map topic into the localizer.

    receive(msg)   the OccupancyGrid checked (a broken map, or one without free space: one error line,
                   nothing changes); then the sensor model says what preparing it costs
                   (``Localizer.map_preparation`` -> ``Preparation(slow, note)``): slow (a range table
                   to build) -> on the map-preparation thread, the note logged, the localizer told a map
                   is on its way (odometry is kept meanwhile, scans cannot be used, an initial pose
                   waits for it); otherwise here
    install        the model's ``prepare`` (any thread), then ``Localizer.set_map``; one line says what
                   was done and whether the node localizes; ``on_installed(map, replacing)`` then lets
                   the node publish its first pose

A map that arrives while an older one is prepared wins: the older one is dropped when its
preparation ends. Every map handled (installed, refused or superseded) counts in ``counts["map"]``.
"""
from __future__ import annotations

import time

from localization.core.occupancy_map import MapError, OccupancyMap
from localization.ros.scan_worker import ScanQueueWorker

TABLE_SOURCES = {"built": "built", "disk": "loaded from the cache", "memory": "shared with a map in memory"}


class MapInstaller:
    """Map messages -> checked, prepared, installed (module docstring); ``stop`` ends its thread."""

    def __init__(self, params, localizer, watchdog, log, counts, on_installed):
        self.params, self.localizer, self.watchdog, self.log = params, localizer, watchdog, log
        self.counts, self.on_installed = counts, on_installed
        self._generation = 0  # of the newest map received: an older one finishing its preparation is dropped
        self.worker = ScanQueueWorker(self._install, log.error, name="map_preparation", depth=1)

    @property
    def idle(self) -> bool:
        """No map waits for or is in its preparation."""
        return self.worker.idle

    def stop(self) -> None:
        self.worker.stop()

    def _refused(self, why: str) -> None:
        self.log.error(f"map on {self.params.map_topic} rejected: {why}")
        self.watchdog.map_failed(time.monotonic(), why)
        self.counts["map"] += 1

    def receive(self, msg) -> None:
        """A map message (the subscription callback's one call)."""
        try:
            occupancy_map = OccupancyMap.from_msg(msg)
        except MapError as exc:
            self._refused(str(exc))
            return
        map_frame = self.params.map_frame
        if occupancy_map.frame_id != map_frame:
            self.log.warning(f"map frame {occupancy_map.frame_id!r} differs from map_frame {map_frame!r}; using it "
                             f"as {map_frame!r}")
        if len(occupancy_map.free_cells) == 0:
            self.log.error(f"map on {self.params.map_topic} rejected: map has no free cell")
            self.counts["map"] += 1
            return
        self._generation += 1
        item = (occupancy_map, self._generation, msg.header.frame_id)
        preparation = self.localizer.map_preparation(occupancy_map)
        if preparation.slow:  # seconds of work: off the executor's thread
            self.localizer.begin_map_preparation()
            self.log.info(f"{preparation.note}; odometry is kept meanwhile, scans cannot be used")
            self.watchdog.map_building(time.monotonic(), "range table")
            self.worker.put(item)
        else:
            self._install(item, time.monotonic())

    def _install(self, item, t_put: float) -> None:  # noqa: ARG002 - the worker's signature
        occupancy_map, generation, frame_id = item
        loc = self.localizer
        t0 = time.monotonic()
        try:
            caster = loc.prepare_ray_caster(occupancy_map)
        except Exception as exc:  # noqa: BLE001 - a map that cannot be prepared is reported, never fatal
            loc.begin_map_preparation(False)
            self._refused(f"preparing its ray caster failed: {exc!r}")
            return
        if generation != self._generation:  # a newer map arrived meanwhile: it will be installed
            self.counts["map"] += 1
            return
        replacing, was_ready = loc.has_map, loc.ready
        try:
            loc.set_map(occupancy_map, caster)
        except MapError as exc:
            loc.begin_map_preparation(False)
            self._refused(str(exc))
            return
        self.watchdog.map_ready(time.monotonic())
        how = TABLE_SOURCES.get(getattr(caster, "table_source", None), "")
        what = f"range table {how} in {time.monotonic() - t0:.1f} s; " if how else ""
        self.log.info(f"{'new ' if replacing else ''}map {occupancy_map.width}x{occupancy_map.height} cells at "
                      f"{occupancy_map.resolution:.4f} m in frame {frame_id or '(none)'}: "
                      f"{what}{'localizing' if loc.ready else 'waiting for an initial pose'}")
        if replacing and was_ready:
            if loc.ready:
                self.log.warning(
                    "new map: the particles are kept where they are (the new map is taken to be in the same "
                    f"frame {self.params.map_frame!r} as the previous one); if it is not, send an initial pose "
                    "or call ~/reinitialize_global_localization")
            else:
                self.log.warning("new map: no particle lies in its free space: waiting for an initial pose")
        self.on_installed(occupancy_map, replacing)
        self.counts["map"] += 1
