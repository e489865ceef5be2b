"""Forward-pass time of the guidance model as the model service runs it (``GuidanceModel.predict``),
back to back and with a pause before each call. With one trainee the service runs one window
every 100 ms, and between calls other processes evict the model's weights from the CPU caches
(3.2 MB for fusion-2x256). Prints one JSON line per case (ms).

    python tests/benchmarks/bench_inference.py [--model PATH] [--dataset DIR] [--threads 1]
        [--batches 1,16,64] [--gaps-ms 0,100] [--calls 200] [--flush-denormal] [--int8] [--onnx]

Windows come from a dataset's records (``--dataset``, real value ranges) or else uniformly from
the model's own scaling range. ``--flush-denormal`` flushes denormals to zero on the calling
thread. ``--int8`` times an int8 dynamically quantised copy (LSTM and head) instead and prints how
far its predictions move from the exported model's (N). ``--onnx`` times the same model exported to
ONNX and run by ONNX Runtime (one intra-op thread) instead, with how far its predictions move
(what ``dhg-serve`` runs on CPU since decision 0030).
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch

from dhg.core.features import FEATURE_NAMES
from dhg.learning.torchscript import load_model
from dhg.learning.weights import default_model_path


def windows_from(dataset: str | None, model, n: int, rng: np.random.Generator) -> np.ndarray:
    """n windows (n, window, 9) in SI units."""
    w = model.window
    if dataset:
        import pyarrow.parquet as pq

        t = pq.read_table(f"{dataset}/records.parquet", columns=list(FEATURE_NAMES))
        x = np.stack([t[c].to_numpy().astype(np.float32) for c in FEATURE_NAMES], axis=1)
        starts = rng.integers(0, len(x) - w, size=n)
        return np.stack([x[s : s + w] for s in starts])
    buffers = dict(model.module.named_buffers())
    lo = np.zeros(len(FEATURE_NAMES), np.float32)
    span = np.ones(len(FEATURE_NAMES), np.float32)
    idx = buffers["in_idx"].numpy()
    lo[idx], span[idx] = buffers["in_lo"].numpy(), buffers["in_span"].numpy()
    return (lo + span * rng.random((n, w, len(FEATURE_NAMES)))).astype(np.float32)


def int8_copy(model):
    """The exported model rebuilt in eager mode with int8 dynamic quantisation of the LSTM and head."""
    import dataclasses

    from dhg.learning.network import ForcePredictor, LSTMRegressor, MinMaxScaler, ModelConfig

    names = {f.name for f in dataclasses.fields(ModelConfig)}
    raw = model.meta["model_config"]
    cfg = ModelConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in raw.items() if k in names})
    eager = ForcePredictor(LSTMRegressor(cfg), MinMaxScaler(), cfg)
    eager.load_state_dict(model.module.state_dict())
    eager.eval()
    return torch.ao.quantization.quantize_dynamic(eager, {torch.nn.LSTM, torch.nn.Linear}, dtype=torch.qint8)


def onnx_predict(model):
    """The exported model through ONNX Runtime (fp32, one thread): windows (B, T, 9) -> (B, 3) N."""
    import io

    import onnxruntime as ort

    buf = io.BytesIO()
    torch.onnx.export(
        model.module,
        (torch.zeros(2, model.window, 9),),
        buf,
        dynamo=False,  # TorchScript in, so the TorchScript-based exporter
        input_names=["windows"],
        output_names=["force"],
        dynamic_axes={"windows": {0: "batch"}, "force": {0: "batch"}},
        opset_version=17,
    )
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = opts.inter_op_num_threads = 1
    sess = ort.InferenceSession(buf.getvalue(), opts, providers=["CPUExecutionProvider"])
    return lambda x: sess.run(None, {"windows": np.ascontiguousarray(x, np.float32)})[0].astype(np.float64)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model", default=str(default_model_path()))
    p.add_argument("--dataset", help="a dataset folder to draw windows from")
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads (dhg-serve's default on 2 cores: 1)")
    p.add_argument("--batches", default="1,16,64")
    p.add_argument("--gaps-ms", default="0,100", help="pause before each call (ms)")
    p.add_argument("--calls", type=int, default=200)
    p.add_argument("--device", default="cpu")
    p.add_argument("--flush-denormal", action="store_true", help="flush denormals to zero (this thread)")
    p.add_argument("--int8", action="store_true", help="time an int8 dynamically quantised copy instead")
    p.add_argument("--onnx", action="store_true", help="time the model run by ONNX Runtime instead")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    torch.set_flush_denormal(args.flush_denormal)
    model = load_model(args.model, device=args.device)
    rng = np.random.default_rng(0)
    pool = windows_from(args.dataset, model, 4096, rng)
    predict = model.predict
    if args.int8:
        quantised = int8_copy(model)

        def predict(x: np.ndarray) -> np.ndarray:
            with torch.no_grad():
                return quantised(torch.from_numpy(np.ascontiguousarray(x))).double().numpy()

        d = np.abs(predict(pool) - model.predict(pool))
        print(json.dumps({"int8_vs_fp32_rms_n": float(np.sqrt((d**2).mean())), "int8_vs_fp32_max_n": float(d.max())}))
    if args.onnx:
        predict = onnx_predict(model)
        d = np.abs(predict(pool) - model.predict(pool))
        print(
            json.dumps(
                {
                    "onnx_vs_torchscript_rms_n": float(np.sqrt((d**2).mean())),
                    "onnx_vs_torchscript_max_n": float(d.max()),
                }
            )
        )
    for _ in range(3):  # TorchScript's profiling executor optimises on the first calls
        predict(pool[:1])
    for gap_ms in (float(g) for g in args.gaps_ms.split(",")):
        for batch in (int(b) for b in args.batches.split(",")):
            times = []
            for k in range(args.calls):
                x = pool[(k * batch) % (len(pool) - batch) :][:batch]
                if gap_ms:
                    time.sleep(gap_ms * 1e-3)
                t0 = time.perf_counter()
                predict(x)
                times.append(time.perf_counter() - t0)
            t = np.array(times[5:]) * 1e3
            row = {
                "model": model.meta.get("preset"),
                "device": model.device,
                "threads": args.threads,
                "windows": "dataset" if args.dataset else "uniform",
                "int8": args.int8,
                "onnx": args.onnx,
                "flush_denormal": args.flush_denormal,
                "batch": batch,
                "gap_ms": gap_ms,
                "p50_ms": round(float(np.percentile(t, 50)), 3),
                "p99_ms": round(float(np.percentile(t, 99)), 3),
            }
            print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
