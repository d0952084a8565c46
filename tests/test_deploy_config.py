"""What `DASK_CONFIG=deploy/dask` gives Dask: only Dask configuration (no Kubernetes spec
merged into it), and the SLURM worker size `swathflow run --cluster slurm` submits."""
from pathlib import Path

import pytest

DASK_DIR = Path(__file__).resolve().parents[1] / "deploy" / "dask"


def test_dask_config_folder_holds_only_dask_configuration():
    import dask.config
    cfg = dask.config.collect(paths=[str(DASK_DIR)], env={})
    assert set(cfg) == {"distributed", "temporary-directory", "jobqueue"}, set(cfg)
    assert not {"apiVersion", "kind", "spec", "metadata"} & set(cfg)
    assert cfg["distributed"]["scheduler"]["allowed-failures"] == 5
    slurm = cfg["jobqueue"]["slurm"]
    assert (slurm["cores"], slurm["processes"], slurm["memory"]) == (1, 1, "2GB")
    assert slurm["scheduler-options"]["host"] == "127.0.0.1"


def test_slurm_options_fill_only_what_the_configuration_leaves_unset():
    import dask.config
    from swathflow.cluster import slurm_options
    with dask.config.set({"jobqueue.slurm.cores": None, "jobqueue.slurm.memory": None,
                          "jobqueue.slurm.processes": None}):
        assert slurm_options() == {"cores": 1, "processes": 1, "memory": "2GB"}
    with dask.config.set({"jobqueue.slurm.cores": 4, "jobqueue.slurm.memory": "16GB",
                          "jobqueue.slurm.processes": 2}):
        assert slurm_options() == {}


def test_unknown_cluster_kind_is_a_clear_error():
    from swathflow.cluster import dask_client
    from swathflow.errors import SwathflowError
    with pytest.raises(SwathflowError, match="unknown cluster 'pbs'"):
        with dask_client(cluster="pbs"):
            pass
