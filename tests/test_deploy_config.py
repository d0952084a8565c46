"""What `DASK_CONFIG=deploy/dask` gives Dask: only Dask configuration (no Kubernetes spec
merged into it), and the SLURM worker size `swathflow run --cluster slurm` submits; the
Prefect deployments of deploy/prefect.yaml load from any folder and describe every
parameter."""
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


def test_prefect_deployments_load_from_any_folder_with_described_parameters(tmp_path,
                                                                           monkeypatch):
    """Each deployment's entrypoint is a module of the installed package (not a path of
    the repository), so `prefect deploy --prefect-file .../prefect.yaml` works from any
    folder; Prefect shows a description for every parameter, and `cluster` as a choice."""
    import yaml
    from prefect.flows import load_flow_from_entrypoint
    from prefect.utilities.callables import parameter_schema
    doc = yaml.safe_load((DASK_DIR.parent / "prefect.yaml").read_text())
    monkeypatch.chdir(tmp_path)
    names = {d["name"]: d for d in doc["deployments"]}
    assert {"inbox", "mission"} <= set(names)
    for d in names.values():
        assert ".py" not in d["entrypoint"] and "/" not in d["entrypoint"], d["entrypoint"]
        flow = load_flow_from_entrypoint(d["entrypoint"])
        props = parameter_schema(flow.fn).model_dump()["properties"]
        undescribed = [k for k, v in props.items() if not v.get("description")]
        assert not undescribed, (d["name"], undescribed)
        assert set(d.get("parameters", {})) <= set(props)
    mission = load_flow_from_entrypoint(names["mission"]["entrypoint"])
    cluster = parameter_schema(mission.fn).model_dump()["properties"]["cluster"]
    assert cluster["enum"] == ["local", "slurm"]
