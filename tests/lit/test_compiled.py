"""The training step's forward compiled whole (:mod:`unicorn.lit.compiled`): one graph per step kind without a
graph break, no new graph once warm, graphs that CUDA graphs can capture and replay (the state they change written in
place, no op inductor or the cudagraphs backend refuses to capture, no tensor on the host), and the eager steps'
losses and gradients (traced and differentiated without generated code: the ``aot_eager`` backend)."""

from __future__ import annotations

import copy

import pytest
import torch
from torch._dynamo.backends.debugging import aot_eager, boxed_nop
from torch._dynamo.utils import counters
from torch._guards import TracingContext
from torch._inductor.utils import any_is_symbolic, get_first_incompatible_cudagraph_node

from tests.support.model import IMAGE_SIZE, randomize_heads, tiny_config
from unicorn.hostsync import sync_free
from unicorn.lit.compiled import CompiledStep
from unicorn.model import Unicorn
from unicorn.objectives import Objectives
from unicorn.render import OverflowCounter

BATCH = 4


@pytest.fixture
def images() -> torch.Tensor:
    return torch.rand(BATCH, 3, IMAGE_SIZE, IMAGE_SIZE, generator=torch.Generator().manual_seed(1))


def _setup():
    torch.manual_seed(0)
    model = Unicorn(tiny_config())
    randomize_heads(model, std=0.1)
    model.set_active_dims(shape=2, texture=8)
    # a memory of two batches (the third push writes over the first); one viewpoint bin (the neighbours' bin draw,
    # torch.multinomial, which a compiled graph draws from the random stream otherwise than eagerly, has one outcome)
    loss = {**model.config["loss"], "neighbor_weight": 1.0, "n_bins": 1, "memory_size": 2 * BATCH}
    return model, Objectives.from_config(loss, model)


def _run(model, objectives, forward, kind, images, step):
    """One step's losses and gradients (``forward`` None: the eager objectives)."""
    model.zero_grad(set_to_none=True)
    torch.manual_seed(100 + step)
    with sync_free(forward is not None), OverflowCounter():
        if forward is None:
            losses = objectives(kind, model, images, iteration=step)
        else:
            losses = forward(kind, images, False, step)
        losses["total"].backward()
    grads = {name: p.grad.clone() for name, p in model.named_parameters() if p.grad is not None}
    return {k: v.detach().clone() for k, v in losses.items()}, grads


def test_a_compiled_step_is_one_graph_and_gives_the_eager_losses_and_gradients(images):
    model, objectives = _setup()
    twin = copy.deepcopy((model, objectives))
    graphs, uncapturable = [], []
    addresses: list[list[tuple[int, ...]]] = []  # per forward graph, per call: its static inputs' addresses

    def no_uncapturable_op(gm, example_inputs):
        # what inductor checks of each graph before it uses CUDA graphs: no op that reads the device or makes a
        # tensor of data-dependent size (get_first_incompatible_cudagraph_node), no dynamic shape
        node = get_first_incompatible_cudagraph_node(gm)
        uncapturable.extend([f"op {node.target}: {node.meta.get('stack_trace', '')}"] if node is not None else [])
        uncapturable.extend(["dynamic shapes"] if any_is_symbolic(*example_inputs) else [])

    def backward(gm, example_inputs):
        no_uncapturable_op(gm, example_inputs)
        return boxed_nop(gm, example_inputs)

    def capturable(gm, example_inputs):
        # what torch.compile's CUDA graphs (cudagraph trees) need of a forward graph: tensor or size inputs, inputs
        # changed in place only where they are static (the tensors of the modules: parameters, buffers, the neighbour
        # memory), and static inputs at the same addresses at every call (elsewhere the graph is recorded again)
        no_uncapturable_op(gm, example_inputs)
        meta = TracingContext.try_get().fw_metadata
        static = list(meta.static_input_indices)
        changed = {i for i, info in enumerate(meta.input_info) if info.mutates_data or info.mutates_metadata}
        uncapturable.extend(f"input {i} changed in place" for i in sorted(changed - set(static)))
        uncapturable.extend(type(x).__name__ for x in example_inputs if not isinstance(x, (torch.Tensor, torch.SymInt)))
        forward, calls = boxed_nop(gm, example_inputs), []
        addresses.append(calls)

        def run(args):
            calls.append(tuple(args[i].data_ptr() for i in static if isinstance(args[i], torch.Tensor)))
            return forward(args)

        run._boxed_call = True
        return run

    def counting(gm, example_inputs):
        graphs.append(gm)
        return aot_eager(gm, example_inputs, fw_compiler=capturable, bw_compiler=backward)

    compiled = CompiledStep(twin[1], twin[0], backend=counting, copy_outputs=True)  # the copies CUDA graphs need
    counters.clear()
    seen = []
    for step, kind in enumerate(["pose", "3d"] * 3):
        checked = step < 2  # the trainer's first steps: eager, with their reads (they size the fixed buffers)
        losses, grads = _run(model, objectives, None, kind, images, step)
        got_losses, got_grads = _run(*twin, None if checked else compiled, kind, images, step)
        seen.append(len(graphs))
        assert got_losses.keys() == losses.keys() and got_grads.keys() == grads.keys()
        for name, value in losses.items():
            torch.testing.assert_close(got_losses[name], value, rtol=1e-5, atol=1e-6, msg=f"{step} {name}")
        for name, value in grads.items():  # float32 rounding of another order of the same operations
            scale = value.abs().max().clamp_min(1e-12)
            assert (got_grads[name] - value).abs().max() <= 1e-4 * scale, (step, name)
        # a plain update, and both at the same state for the next step
        with torch.no_grad():
            for p in model.parameters():
                if p.grad is not None:
                    p -= 0.05 * p.grad
            # in place: load_state_dict would drop the code masks' host copies, which the checked steps refill
            for a, b in zip([*model.parameters(), *model.buffers()], [*twin[0].parameters(), *twin[0].buffers()]):
                b.copy_(a)
        twin[1].memory.load_state(objectives.memory.state())
    assert not counters["graph_break"], dict(counters["graph_break"])  # the whole forward in one graph
    assert seen == [0, 0, 1, 2, 2, 2]  # one graph per step kind, none after
    assert len(addresses) == 2 and not uncapturable, uncapturable
    assert [len(calls) for calls in addresses] == [2, 2] and all(len(set(calls)) == 1 for calls in addresses)


@pytest.mark.filterwarnings("ignore:.*an autograd kernel was not registered:UserWarning")  # meta kernels
def test_a_compiled_step_on_another_device_holds_no_host_tensor(images):
    # torch.compile uses CUDA graphs only for graphs without a tensor on the host ("skipping cudagraphs due to cpu
    # device"), a module's constant included; the meta device, compiled like CUDA, stands in for it on the CPU
    model, objectives = _setup()
    for step, kind in enumerate(["pose", "3d"]):  # the checked steps, on the CPU: they size the fixed buffers
        _run(model, objectives, None, kind, images, step)
    model.to("meta")
    objectives.to("meta")
    on_host: list[str] = []

    def devices(gm, example_inputs):
        for node in gm.graph.nodes:
            value = node.meta.get("val")
            for t in value if isinstance(value, (list, tuple)) else [value]:
                if isinstance(t, torch.Tensor) and t.device.type != "meta":
                    where = node.meta.get("stack_trace", "")
                    on_host.append(f"{node.op} {node.target} {tuple(t.shape)} on {t.device}: {where}")
        return boxed_nop(gm, example_inputs)

    graphs = []

    def backend(gm, example_inputs):
        graphs.append(gm)
        return aot_eager(gm, example_inputs, fw_compiler=devices, bw_compiler=devices)

    compiled = CompiledStep(objectives, model, backend=backend, copy_outputs=True)
    for step, kind in enumerate(["pose", "3d"], start=2):
        losses, grads = _run(model, objectives, compiled, kind, images.to("meta"), step)
        assert {v.device.type for v in [*losses.values(), *grads.values()]} == {"meta"}
    assert len(graphs) == 2 and not on_host, on_host


@pytest.mark.parametrize("keep_mutations", [None, True], ids=["cudagraphs-backend", "mutations-kept"])
def test_the_cudagraphs_backend_finds_nothing_that_stops_it_capturing(images, keep_mutations):
    # model.compile=cudagraphs: torch's cudagraphs backend records a graph only where its check_for_skip finds no
    # input changed inside the graph (modules inlined, no input counts as fixed; the backend has AOTAutograd apply
    # the changes after the graph: cudagraph_backend_keep_input_mutation) and no op it cannot capture; the host
    # tensors it also refuses are the meta test's above. Kept in the graph, as aot_eager and inductor keep them, the
    # changes to the modules' buffers are found: the check sees the graphs
    from torch._dynamo.backends.common import aot_autograd
    from torch._dynamo.backends.cudagraphs import check_for_mutation_ignore_cuda_graph_managed_tensor
    from torch._inductor.utils import count_tangents, num_fw_fixed_arguments

    if keep_mutations is None:
        keep_mutations = torch._dynamo.config.cudagraph_backend_keep_input_mutation
    model, objectives = _setup()
    for step, kind in enumerate(["pose", "3d"]):  # the checked steps: they size the fixed buffers
        _run(model, objectives, None, kind, images, step)
    skips: list[tuple[str, str]] = []

    def skip(gm, fixed: int) -> str:
        node = get_first_incompatible_cudagraph_node(gm)
        mutation = check_for_mutation_ignore_cuda_graph_managed_tensor(gm, fixed)
        return mutation or (f"op {node.target}" if node is not None else "")

    def backend(gm, example_inputs):
        def forward(fw, fw_inputs):
            skips.append(("forward", skip(fw, num_fw_fixed_arguments(len(example_inputs), len(fw_inputs)))))
            return boxed_nop(fw, fw_inputs)

        def backward(bw, bw_inputs):
            skips.append(("backward", skip(bw, count_tangents(bw))))
            return boxed_nop(bw, bw_inputs)

        keep = {"keep_inference_input_mutations": keep_mutations}
        return aot_autograd(fw_compiler=forward, bw_compiler=backward, **keep)(gm, example_inputs)

    compiled = CompiledStep(objectives, model, backend=backend, copy_outputs=True)
    for step, kind in enumerate(["pose", "3d"], start=2):
        _run(model, objectives, compiled, kind, images, step)
    assert [graph for graph, _ in skips] == ["forward", "backward"] * 2
    found = [why for _, why in skips]
    if keep_mutations:
        assert all("mutated inputs" in why for why in found[::2]) and not any(found[1::2]), found
    else:
        assert not any(found), found


def test_both_averaging_choices_run_one_graph_with_the_eager_losses(images):
    # the texture-averaging choice is a tensor input of the compiled step, selected on the device: a Python bool
    # would be guarded on, a graph (and on CUDA a capture) for each choice
    model, objectives = _setup()
    twin = copy.deepcopy((model, objectives))
    graphs = []

    def counting(gm, example_inputs):
        graphs.append(gm)
        return aot_eager(gm, example_inputs)

    compiled = CompiledStep(twin[1], twin[0], backend=counting)
    for step, kind in enumerate(["pose", "3d"]):  # the checked steps: they size the fixed buffers
        _run(model, objectives, None, kind, images, step)
        _run(*twin, None, kind, images, step)
    eager = {}
    for step, (kind, average) in enumerate([("pose", True), ("pose", False), ("3d", False), ("3d", True)], start=2):
        results = []
        for forward in (None, compiled):
            torch.manual_seed(100 + step)
            with sync_free(forward is not None), OverflowCounter():
                if forward is None:
                    losses = objectives(kind, model, images, average_texture=average, iteration=step)
                else:
                    losses = forward(kind, images, average, step)
            results.append(losses)
        for name, value in results[0].items():
            torch.testing.assert_close(results[1][name], value, rtol=1e-5, atol=1e-6, msg=f"{kind} {average} {name}")
        eager[kind, average] = results[0]["rgb"]
        twin[1].memory.load_state(objectives.memory.state())
    assert len(graphs) == 2  # one per step kind
    assert not torch.equal(eager["pose", True], eager["pose", False])  # the choice changes the renders


@pytest.mark.parametrize(
    ("mode", "options", "captures"),
    [
        ("default", {"mode": "default"}, False),
        ("reduce-overhead", {"mode": "reduce-overhead"}, True),
        ("cudagraphs", {"backend": "cudagraphs"}, True),
    ],
)
def test_each_compile_mode_names_its_torch_compile_arguments(monkeypatch, mode, options, captures):
    import unicorn.lit.compiled as compiled_module

    given = []
    monkeypatch.setattr(compiled_module.torch, "compile", lambda fn, **kwargs: given.append(kwargs) or fn)
    model, objectives = _setup()
    step = CompiledStep(objectives, model, mode)
    assert given == [options] and step.captures is captures
    with pytest.raises(ValueError, match="compile mode must be one of"):
        CompiledStep(objectives, model, "fastest")
