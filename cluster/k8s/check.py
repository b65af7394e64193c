#!/usr/bin/env python3
"""Validate matflow's Kubernetes manifests offline.

    python3 cluster/k8s/check.py [KUSTOMIZATION_DIR] [--kubernetes-version 1.32.0]

1. Renders the kustomization with `kubectl kustomize` (a throwaway copy
   with a generated token file when the folder has none).
2. Validates every rendered object against the Kubernetes API schema of
   the given version, strictly (unknown fields are errors), with the
   `kubernetes-validate` package (PyPI).
3. Checks what a schema cannot: every Secret, PersistentVolumeClaim and
   Service a pod or argument names exists in the render; every Service
   selects some pod template and its target ports are ports those
   containers declare; `--workers=dns:NAME:PORT` names a headless Service
   on that port; `--remote-cache=grpc://NAME:PORT` names a Service port;
   an Indexed Job's completions equal its `--shards`; a worker listening
   beyond loopback has a token file on a mounted Secret; every matflow
   image was rewritten by `images:`; every container runs as non-root
   with a read-only root filesystem.

Exits 1 naming each problem; 0 when all hold.
"""
import argparse
import os
import shutil
import subprocess
import sys
import tempfile

import yaml


def render(src):
    with tempfile.TemporaryDirectory() as tmp:
        d = os.path.join(tmp, "k8s")
        shutil.copytree(src, d)
        if not os.path.exists(os.path.join(d, "token")):
            with open(os.path.join(d, "token"), "w") as f:
                f.write(os.urandom(16).hex())
        kubectl = shutil.which("kubectl")
        if kubectl is None:
            sys.exit("kubectl not found: apt-get install kubernetes-client (or any kubectl >= 1.14)")
        out = subprocess.run([kubectl, "kustomize", d], capture_output=True, text=True)
        if out.returncode != 0:
            sys.exit(f"kubectl kustomize {src} failed:\n{out.stderr}")
        with open(os.path.join(tmp, "rendered.yaml"), "w") as f:
            f.write(out.stdout)
        return out.stdout


def schema_validate(text, version):
    with tempfile.NamedTemporaryFile("w", suffix=".yaml", delete=False) as f:
        f.write(text)
        path = f.name
    try:
        exe = shutil.which("kubernetes-validate")
        cmd = [exe] if exe else [sys.executable, "-m", "kubernetes_validate"]
        out = subprocess.run(cmd + ["--strict", "-k", version, path], capture_output=True, text=True)
        if out.returncode != 0:
            return [f"kubernetes-validate --strict -k {version}:\n{out.stdout}{out.stderr}"]
        return []
    finally:
        os.unlink(path)


def pod_specs(objs):
    for o in objs:
        k = o.get("kind")
        if k in ("Deployment", "StatefulSet", "DaemonSet", "Job"):
            yield o, o["spec"]["template"]
        elif k == "Pod":
            yield o, o


def args_of(container):
    out = {}
    for a in container.get("args", []) or []:
        if a.startswith("--") and "=" in a:
            k, v = a[2:].split("=", 1)
            out[k] = v
    return out


def cross_check(objs):
    errs = []
    names = {(o["kind"], o["metadata"]["name"]) for o in objs}
    services = {o["metadata"]["name"]: o for o in objs if o["kind"] == "Service"}
    pods = list(pod_specs(objs))

    def has(kind, name):
        return (kind, name) in names

    for owner, tpl in pods:
        who = f'{owner["kind"]}/{owner["metadata"]["name"]}'
        spec = tpl["spec"]
        vols = {v["name"]: v for v in spec.get("volumes", []) or []}
        for v in vols.values():
            if "secret" in v and not has("Secret", v["secret"]["secretName"]):
                errs.append(f'{who}: volume {v["name"]} names Secret {v["secret"]["secretName"]}, not in the render')
            pvc = v.get("persistentVolumeClaim")
            if pvc and not has("PersistentVolumeClaim", pvc["claimName"]):
                errs.append(f'{who}: volume {v["name"]} names PVC {pvc["claimName"]}, not in the render')
        for c in spec["containers"]:
            cw = f'{who} container {c["name"]}'
            for m in c.get("volumeMounts", []) or []:
                if m["name"] not in vols:
                    errs.append(f'{cw}: mounts {m["name"]}, not a volume of the pod')
            sc = c.get("securityContext", {}) or {}
            psc = spec.get("securityContext", {}) or {}
            if not (sc.get("runAsNonRoot") or psc.get("runAsNonRoot")):
                errs.append(f"{cw}: not runAsNonRoot")
            if not sc.get("readOnlyRootFilesystem"):
                errs.append(f"{cw}: root filesystem writable")
            image = c["image"]
            a = args_of(c)
            is_matflow = (c.get("args") or [None])[0] in ("run", "worker")
            if is_matflow and image == "matflow":
                errs.append(f"{cw}: image 'matflow' not rewritten by images:")
            if not is_matflow:
                continue
            mounts = [m["mountPath"] for m in c.get("volumeMounts", []) or []]
            # Every Service a matflow argument names must exist on that port.
            for key in ("remote-cache",):
                if key in a:
                    ep = a[key].split("://", 1)[-1]
                    host, _, port = ep.rpartition(":")
                    svc = services.get(host)
                    if svc is None:
                        errs.append(f"{cw}: --{key}={a[key]}: no Service {host}")
                    elif int(port) not in [p["port"] for p in svc["spec"]["ports"]]:
                        errs.append(f"{cw}: --{key}={a[key]}: Service {host} has no port {port}")
            if "workers" in a:
                for w in a["workers"].split(","):
                    if not w.startswith("dns:"):
                        continue
                    host, _, port = w[4:].rpartition(":")
                    svc = services.get(host)
                    if svc is None:
                        errs.append(f"{cw}: --workers={w}: no Service {host}")
                        continue
                    if svc["spec"].get("clusterIP") != "None":
                        errs.append(f"{cw}: --workers={w}: Service {host} is not headless, so DNS gives one address, not one per worker")
                    if int(port) not in [p["port"] for p in svc["spec"]["ports"]]:
                        errs.append(f"{cw}: --workers={w}: Service {host} has no port {port}")
            for key in ("token-file",):
                if key in a and not any(a[key].startswith(m.rstrip("/") + "/") for m in mounts):
                    errs.append(f"{cw}: --{key}={a[key]} is on no mounted volume")
            if c["args"][0] == "worker":
                listen = a.get("listen", "127.0.0.1:0")
                if not listen.startswith("127.") and "token-file" not in a and "insecure" not in c["args"]:
                    errs.append(f"{cw}: listens on {listen} without a token")
                lport = int(listen.rpartition(":")[2])
                if lport not in [p["containerPort"] for p in c.get("ports", []) or []]:
                    errs.append(f"{cw}: listens on {lport}, not a declared containerPort")
            if owner["kind"] == "Job" and owner["spec"].get("completionMode") == "Indexed":
                if "shards" not in a:
                    errs.append(f"{cw}: an Indexed Job without --shards")
                elif int(a["shards"]) != owner["spec"]["completions"]:
                    errs.append(f'{cw}: --shards={a["shards"]} but completions {owner["spec"]["completions"]}')
                if a.get("shard") != "$(JOB_COMPLETION_INDEX)":
                    errs.append(f"{cw}: --shard is not the completion index")
    # Every Service selects a pod template, on ports its containers declare.
    for name, svc in services.items():
        sel = svc["spec"].get("selector") or {}
        matches = [
            tpl for _, tpl in pods
            if all((tpl["metadata"].get("labels") or {}).get(k) == v for k, v in sel.items())
        ]
        if not matches:
            errs.append(f"Service/{name}: selector {sel} matches no pod template")
            continue
        declared = set()
        for tpl in matches:
            for c in tpl["spec"]["containers"]:
                for p in c.get("ports", []) or []:
                    declared.add(p.get("name"))
                    declared.add(p["containerPort"])
        for p in svc["spec"]["ports"]:
            if p.get("targetPort", p["port"]) not in declared:
                errs.append(f'Service/{name}: targetPort {p.get("targetPort")} is no port of the pods it selects')
    return errs


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dir", nargs="?", default=os.path.dirname(os.path.abspath(__file__)))
    ap.add_argument("--kubernetes-version", default="1.32.0")
    a = ap.parse_args()
    text = render(a.dir)
    objs = [o for o in yaml.safe_load_all(text) if o]
    errs = schema_validate(text, a.kubernetes_version)
    errs += cross_check(objs)
    kinds = sorted(f'{o["kind"]}/{o["metadata"]["name"]}' for o in objs)
    if errs:
        for e in errs:
            print(f"error: {e}")
        sys.exit(1)
    print(f"{len(objs)} objects valid for Kubernetes {a.kubernetes_version}: {', '.join(kinds)}")


if __name__ == "__main__":
    main()
