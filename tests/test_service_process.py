"""The terrain service as its own process, the way the demo and deployments run it."""

import numpy as np
import pytest

from client.terrain_client import TerrainClient
from server.process import ServiceProcess
from sortie.errors import SortieError
from terrain.dem import read_dem
from terrain.terrain import Terrain


def test_service_process_serves_and_stops_cleanly(hgt_alps, tmp_path):
    log = tmp_path / "service.log"
    with ServiceProcess(["terrain", "serve", "--dem", str(hgt_alps)], log=log) as service:
        lat = np.array([47.0, 47.5, 47.999])
        lon = np.array([9.0, 9.25, 9.5])
        with TerrainClient(service.address) as client:
            remote = client.heights(lat, lon)
        local = Terrain([read_dem(hgt_alps)]).heights(lat, lon)
        np.testing.assert_array_equal(remote.height_msl_m, local.height_msl_m)
    assert service.proc.returncode == 0  # SIGTERM drains and exits cleanly
    assert str(service.port) in log.read_text()


def test_service_process_that_cannot_start_says_so(tmp_path):
    with pytest.raises(SortieError, match="exited with code"):
        with ServiceProcess(["terrain", "serve", "--dem", str(tmp_path / "missing.hgt")], start_timeout_s=30):
            pass
