"""deploy/k8s/ checked against the Kubernetes API schemas that kubernetes-validate bundles (no
cluster and no network needed), strictly (an unknown field is an error), for the oldest
Kubernetes the deployment docs support and the newest bundled; and a deliberately broken copy
fails, so the check can fail."""

import pathlib
import shutil

import kubernetes_validate
import pytest
import yaml

K8S = pathlib.Path(__file__).resolve().parents[2] / "deploy" / "k8s"
# docs/deployment.md: kubectl 1.27+.
VERSIONS = ("1.27.0", kubernetes_validate.latest_version())


def manifest_errors(folder: pathlib.Path) -> list[str]:
    """One line per problem of the manifests in `folder`: schema violations of every document
    of every *.yaml but the kustomization, and kustomization resources that are missing or
    files it leaves out."""
    errors = []
    kustomization = yaml.safe_load((folder / "kustomization.yaml").read_text())
    listed = set(kustomization["resources"])
    manifests = sorted(path for path in folder.glob("*.yaml") if path.name != "kustomization.yaml")
    for name in sorted(listed - {path.name for path in manifests}):
        errors.append(f"kustomization.yaml lists {name}, which does not exist")
    for path in manifests:
        if path.name not in listed:
            errors.append(f"kustomization.yaml does not list {path.name}")
        for index, document in enumerate(yaml.safe_load_all(path.read_text())):
            for version in VERSIONS:
                try:
                    kubernetes_validate.validate(document, version, strict=True)
                except kubernetes_validate.ValidationError as error:
                    where = ".".join(str(part) for part in error.path)
                    errors.append(f"{path.name}[{index}] (Kubernetes {version}) {where}: {error.message}")
                except kubernetes_validate.SchemaNotFoundError as error:
                    errors.append(f"{path.name}[{index}] (Kubernetes {version}): no schema: {error}")
    return errors


def test_manifests_match_the_kubernetes_schemas():
    assert manifest_errors(K8S) == []


@pytest.mark.parametrize(
    "file, old, new, expected",
    [
        ("deployment.yaml", "terminationGracePeriodSeconds:", "terminationGracePeriod:", "terminationGracePeriod"),  # Misspelt field.
        ("deployment.yaml", "containerPort: 50051", "containerPort: fifty", "containerPort"),  # Wrong type.
        ("service.yaml", "kind: Service", "kind: Servize", "no schema"),  # Unknown kind.
        ("kustomization.yaml", "- pdb.yaml", "- pdbs.yaml", "pdbs.yaml"),  # Dangling resource.
    ],
)
def test_a_broken_manifest_fails(tmp_path, file, old, new, expected):
    broken = tmp_path / "k8s"
    shutil.copytree(K8S, broken)
    text = (broken / file).read_text()
    assert old in text, f"{file} no longer has {old!r}; update this test"
    (broken / file).write_text(text.replace(old, new, 1))
    errors = manifest_errors(broken)
    assert errors and any(expected in error for error in errors), errors
