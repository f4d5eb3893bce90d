"""The LTX-2 and HunyuanVideo-1.5 backends (diffusers + peft) on tiny random-weight models of the real classes: the
interface, the time convention at the boundary, LoRA on video attention with the Demonstrator = adapters off, LoRA
files, and one WMSD step through train.py. Skipped where the optional packages of requirements-real.txt are absent
(CI installs them)."""
import importlib.util
import inspect
import json
import re
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from PIL import Image

pytest.importorskip("diffusers")
pytest.importorskip("peft")
pytest.importorskip("av")      # PyAV: the +SFT videos in mp4 and other containers

import distill  # noqa: E402
import models  # noqa: E402
import reward  # noqa: E402
import rl  # noqa: E402
import train  # noqa: E402
import world  # noqa: E402
from conftest import run  # noqa: E402


def _tiny(cls):
    m = cls.tiny(world.VOCAB + ["[", "]:"])
    pairs = world.make_pairs(2, seed=0, error_rate=0.0)
    f0 = np.stack([p.frame0 for p in pairs])
    return m, f0, m.condition(f0, [p.task.text for p in pairs]), m.condition(f0, [p.d_oracle for p in pairs])


@pytest.fixture(scope="module")
def ltx():
    return _tiny(models.LTX2Video)


@pytest.fixture(scope="module")
def hy():
    return _tiny(models.HunyuanVideo15)


LORA_NAMES = {  # Table 3: LoRA on the video stream's attention only
    "ltx": r"transformer_blocks\.\d+\.attn[12]\.(to_q|to_k|to_v|to_out\.0)\.lora_[AB]\..*",
    "hy": r"transformer_blocks\.\d+\.attn\.(to_q|to_k|to_v|to_out\.0)\.lora_[AB]\..*",
}


def test_velocity_is_converted_once_at_the_boundary(ltx):
    m, f0, c, _ = ltx
    x = torch.randn(2, *m.latent_shape())
    t = torch.tensor([0.25, 0.75])
    with torch.no_grad():
        v = m(x, t, c)
        # the transformer called directly, in diffusers' convention: sigma = 1 - t, first-frame tokens at 0
        z = torch.cat([c["image_latent"], x], dim=2)
        B, C, F, h, w = z.shape
        sig = (1 - t) * m.transformer.config.timestep_scale_multiplier
        ts = sig[:, None].repeat(1, F * h * w)
        ts[:, :h * w] = 0
        out = m.transformer(hidden_states=z.permute(0, 2, 3, 4, 1).reshape(B, -1, C),
                            audio_hidden_states=torch.zeros(B, 1, 4), encoder_hidden_states=c["text"],
                            audio_encoder_hidden_states=c["audio_text"], timestep=ts, audio_timestep=sig, sigma=sig,
                            encoder_attention_mask=c["mask"], audio_encoder_attention_mask=c["mask"], num_frames=F,
                            height=h, width=w, fps=m.fps, audio_num_frames=1, return_dict=False)[0]
    direct = out.reshape(B, F, h, w, C).permute(0, 4, 1, 2, 3)[:, :, 1:]
    assert v.shape == x.shape == (2, *m.latent_shape())
    assert torch.allclose(v, -direct, atol=1e-6)          # d x / d t = - d x / d sigma
    video = m.decode(x, f0)
    assert video.dtype == np.uint8 and video.shape[2:] == (m.height, m.width, 3)
    assert np.array_equal(video[:, 0, ::2, ::2], f0)       # frame 0 is the given observation


def test_ltx2_latents_are_normalised_as_diffusers_pipeline_normalises_them(ltx):
    """LTX2Video._normalise against the LTX-2 pipeline's own (de)normalisation, per channel with the VAE's latent
    mean and std. The tiny VAE's are 0 and 1, under which any order of the two passes: set them to other values."""
    from diffusers import LTX2ImageToVideoPipeline as P
    m, vae = ltx[0], ltx[0].vae
    kept = vae.latents_mean.clone(), vae.latents_std.clone()
    g = torch.Generator().manual_seed(0)
    try:
        vae.latents_mean.copy_(torch.randn(kept[0].shape, generator=g))
        vae.latents_std.copy_(torch.rand(kept[1].shape, generator=g) + 0.5)
        z, k = torch.randn(2, len(kept[0]), 2, 3, 3, generator=g), vae.config.scaling_factor
        assert torch.allclose(m._normalise(z), P._normalize_latents(z, vae.latents_mean, vae.latents_std, k))
        assert torch.allclose(m._normalise(z, inverse=True),
                              P._denormalize_latents(z, vae.latents_mean, vae.latents_std, k))
        assert not torch.allclose(m._normalise(z), z, atol=0.1)
    finally:
        vae.latents_mean.copy_(kept[0])
        vae.latents_std.copy_(kept[1])


def test_ltx2_encodes_prompts_as_its_pipeline_does(ltx):
    """LTX2Video.condition's text against diffusers' LTX-2 pipeline's own encoding: Gemma's hidden states of every
    layer for prompts padded on the left, through the text connectors told that side. The two prompts differ in
    length, so the padding side shows."""
    from types import SimpleNamespace

    from diffusers import LTX2ImageToVideoPipeline as P
    m, f0, _, _ = ltx
    texts = ["[magenta cross]: stop level with the blue triangle", "[first-person view]: centre the white square"]
    host = SimpleNamespace(tokenizer=m.tokenizer, text_encoder=m.text_encoder)   # what the pipeline's method reads
    emb, mask = P._get_gemma_prompt_embeds(host, texts, max_sequence_length=m.max_len, device="cpu",
                                           dtype=torch.float32)
    assert mask.sum(1).tolist() == [8, 6] and mask[:, -1].all()               # left-padded to 16
    video, audio, cmask = m.connectors(emb, mask, padding_side="left")       # the pipeline: the tokenizer's side
    c = m.condition(f0, texts)
    assert torch.allclose(c["text"], video, atol=1e-6) and torch.allclose(c["audio_text"], audio, atol=1e-6)
    assert torch.equal(c["mask"], cmask)


@pytest.mark.parametrize("cls", [models.LTX2Video, models.HunyuanVideo15])
def test_first_frame_latents_and_decoded_videos_are_the_pipelines(cls):
    """The first frame's VAE latent and the decoded video against diffusers' image-to-video pipelines' own steps:
    the image to [-1, 1] by the pipeline's video processor and encoded to the latent's mode; LTX-2 then normalises
    it per channel with the VAE's latent mean and std (set here to other values than the tiny VAE's 0 and 1),
    HunyuanVideo-1.5 multiplies it by the VAE's scaling factor (the tiny one's is 1.037). Decoding undoes that, and
    the pipeline's postprocess gives the frames in [0, 1], which ours are to uint8's rounding. The first frames are
    at the model's resolution, so no resize differs."""
    from diffusers.video_processor import VideoProcessor
    m = cls.tiny(world.VOCAB + ["[", "]:"])
    vae = m.vae
    f0 = np.stack([p.frame0 for p in world.make_pairs(2, seed=0, error_rate=0.0)]).repeat(2, 1).repeat(2, 2)
    assert f0.shape[1:3] == (m.height, m.width)
    images = [Image.fromarray(f) for f in f0]
    g = torch.Generator().manual_seed(0)
    x = torch.randn(2, *m.latent_shape(), generator=g)
    proc = VideoProcessor(vae_scale_factor=vae.spatial_compression_ratio, resample="bilinear")
    if cls is models.LTX2Video:
        from diffusers import LTX2ImageToVideoPipeline as P
        from diffusers.pipelines.ltx2.pipeline_ltx2_image2video import retrieve_latents
        vae.latents_mean.copy_(torch.randn(vae.latents_mean.shape, generator=g))
        vae.latents_std.copy_(torch.rand(vae.latents_std.shape, generator=g) + 0.5)
        pixels = proc.preprocess(images, height=m.height, width=m.width)
        z = torch.cat([retrieve_latents(vae.encode(im[None, :, None]), None, "argmax") for im in pixels])
        latent = P._normalize_latents(z, vae.latents_mean, vae.latents_std)
        full = P._denormalize_latents(torch.cat([latent, x], 2), vae.latents_mean, vae.latents_std,
                                      vae.config.scaling_factor)
        video = vae.decode(full, None, return_dict=False)[0]
    else:
        from diffusers.pipelines.hunyuan_video1_5.image_processor import HunyuanVideo15ImageProcessor
        from diffusers.pipelines.hunyuan_video1_5.pipeline_hunyuan_video1_5_image2video import \
            HunyuanVideo15ImageToVideoPipeline as P
        assert vae.config.scaling_factor != 1
        proc = HunyuanVideo15ImageProcessor(vae_scale_factor=vae.spatial_compression_ratio, vae_latent_channels=4)
        latent = torch.cat([P._get_image_latents(vae, proc, im, m.height, m.width, "cpu") for im in images])
        video = torch.cat([vae.decode(x[i:i + 1] / vae.config.scaling_factor, return_dict=False)[0] for i in range(2)])
    with torch.no_grad():
        assert torch.allclose(m._image_latent(f0), latent, atol=1e-5)
        ours = m.decode(x, f0)
    want = proc.postprocess_video(video.detach(), output_type="np")           # (B, F, H, W, 3) in [0, 1]
    assert ours.shape == want.shape and np.abs(ours[:, 1:] / 255 - want[:, 1:]).max() <= 0.51 / 255
    assert np.array_equal(ours[:, 0], f0)                                   # frame 0: the given observation


def test_hunyuan15_velocity_and_first_frame_conditioning(hy):
    m, f0, c, _ = hy
    x = torch.randn(2, *m.latent_shape())
    t = torch.tensor([0.25, 0.75])
    with torch.no_grad():
        v = m(x, t, c)
        # the transformer called directly as diffusers' image-to-video pipeline calls it: timestep 1000 sigma,
        # sigma = 1 - t; the first frame's latent as channels at latent frame 0 and a mask channel
        cond = torch.zeros_like(x)
        cond[:, :, 0] = c["image_latent"][:, :, 0]
        mask = torch.zeros_like(x[:, :1])
        mask[:, :, 0] = 1
        out = m.transformer(hidden_states=torch.cat([x, cond, mask], 1), timestep=1000 * (1 - t),
                            encoder_hidden_states=c["text"], encoder_attention_mask=c["mask"],
                            encoder_hidden_states_2=c["text_2"], encoder_attention_mask_2=c["mask_2"],
                            image_embeds=c["image_embeds"], return_dict=False)[0]
        other = m(x, t, m.condition(f0[::-1].copy(), ["[red square]: move to the blue circle"] * 2))
    assert v.shape == x.shape == (2, *m.latent_shape()) and m.latent_shape()[1] == 3   # all latent frames
    assert torch.allclose(v, -out, atol=1e-6)              # d x / d t = - d x / d sigma
    assert not torch.allclose(v, other)                    # the first frame and the text reach the velocity
    assert c["image_embeds"].shape[:2] == (2, 16) and c["text"].shape[0] == 2
    video = m.decode(x, f0)
    assert video.dtype == np.uint8 and video.shape[1:] == (m.frames, m.height, m.width, 3)
    assert np.array_equal(video[:, 0, ::2, ::2], f0)       # frame 0 is the given observation


@pytest.mark.parametrize("backend", ["ltx", "hy"])
def test_lora_on_video_attention_and_the_demonstrator_is_adapters_off(backend, request, tmp_path):
    m, f0, c_E, c_D = request.getfixturevalue(backend)
    x0 = torch.randn(2, *m.latent_shape(), generator=torch.Generator().manual_seed(0))
    t = torch.tensor([0.3, 0.6])
    with torch.no_grad():
        base = m(x0, t, c_E)
    for toy_only in ({"convs": True}, {"embeddings": True}):     # Table 3's LoRA is on Linear layers only
        with pytest.raises(ValueError, match="LoRA on convolutions or embeddings is for the toy"):
            models.add_lora(m, 4, 8.0, **toy_only)
    names = models.add_lora(m, 4, 8.0)
    assert names and all(re.fullmatch(LORA_NAMES[backend], n) for n in names)
    with torch.no_grad():
        assert torch.equal(m(x0, t, c_E), base)            # B = 0: the Executor starts as the base
    params = models.lora_parameters(m)
    assert all(p.requires_grad for p in params)
    assert not any(p.requires_grad for n, p in m.named_parameters() if "lora_" not in n)
    before = {n: p.clone() for n, p in m.named_parameters()}
    # one WMSD update (AWM + anchor, Eq. 12) on Executor rollouts
    xs, ts = distill.rollout(m, x0, c_E, 2)
    loss = rl.final_loss(rl.awm(m, rl.Rollouts(xs, ts, c_E), torch.tensor([1.0, -1.0]), rl.RLConfig())[0],
                         distill.anchor_loss(m, (xs, ts), c_E, c_D), 1.0)
    loss.backward()
    torch.optim.Adam(params, lr=1e-2).step()
    changed = [n for n, p in m.named_parameters() if not torch.equal(p, before[n])]
    assert changed and all("lora_" in n for n in changed)
    with torch.no_grad():
        with models.adapters_disabled(m):
            assert torch.equal(m(x0, t, c_E), base)        # the Demonstrator is untouched
        assert not torch.allclose(m(x0, t, c_E), base)     # the Executor moved
    # LoRA files: only the adapters, round trip, clear errors
    path = tmp_path / "lora.pt"
    models.save_lora(m, str(path), {"note": "x"})
    saved = torch.load(path, weights_only=True)["lora"]
    assert set(saved) == {k for k in m.state_dict() if "lora_" in k}
    with torch.no_grad():
        for p in params:
            p.zero_()
    assert models.load_lora(m, str(path)) == {"note": "x"}
    assert all(torch.equal(m.state_dict()[k], v) for k, v in saved.items())
    (tmp_path / "bad.pt").write_bytes(b"garbage")
    with pytest.raises(ValueError, match="corrupt"):
        models.load_lora(m, str(tmp_path / "bad.pt"))
    with pytest.raises(FileNotFoundError, match="LoRA file .*nope.pt' does not exist"):
        models.load_lora(m, str(tmp_path / "nope.pt"))
    # a file from another model: load_state_dict(strict=False) would skip its weights without a word
    torch.save({"lora": {"blocks.99.lora_A.weight": torch.zeros(1)}, "meta": {}}, tmp_path / "other.pt")
    with pytest.raises(ValueError, match="1 LoRA weights have no place in this model"):
        models.load_lora(m, str(tmp_path / "other.pt"))


def test_a_lora_file_brings_its_runs_rank_and_alpha(tmp_path):
    """bench.py --lora: load_lora(add=True) gives a fresh base adapters of the rank and alpha the file's run used
    (train.py's args in its meta), so the Executor it rebuilds computes the run's velocities -- the alpha scales
    the adapters' output, so a default alpha would compute others."""
    m, f0, c_E, _ = _tiny(models.LTX2Video)
    models.add_lora(m, 4, 3.0)
    for p in models.lora_parameters(m):
        p.data.normal_(0, 0.1, generator=torch.Generator().manual_seed(0))
    models.save_lora(m, str(tmp_path / "lora.pt"), {"args": {"lora_rank": 4, "lora_alpha": 3.0}})
    fresh = models.LTX2Video.tiny(world.VOCAB + ["[", "]:"])
    models.load_lora(fresh, str(tmp_path / "lora.pt"), add=True)
    x, t = torch.randn(2, *m.latent_shape(), generator=torch.Generator().manual_seed(1)), torch.tensor([0.3, 0.6])
    with torch.no_grad():
        assert torch.allclose(fresh(x, t, c_E), m(x, t, c_E), atol=1e-6)
        with models.adapters_disabled(m):
            assert not torch.allclose(fresh(x, t, c_E), m(x, t, c_E), atol=1e-4)   # the adapters matter


@pytest.mark.parametrize("flags", [False, True])
def test_the_loaders_checkpoint_and_offload_when_asked(flags, monkeypatch):
    """train.load_base and make_judge (train.py's and bench.py's loaders) wire --grad_checkpoint into the
    transformer, --offload_text into models.offload of the text encoder and --offload_judge of the VLM, and do none
    of it unasked; bench.py hands its two offload flags to them. (On this machine offloading moves nothing, so the
    call itself is what is checked.)"""
    import bench
    offloaded = []
    monkeypatch.setattr(models, "offload", offloaded.append)
    m = train.load_base(train.Args(model="ltx2-tiny", grad_checkpoint=flags, offload_text=flags))
    judge = train.make_judge(train.Args(judge="qwen-vl-tiny", offload_judge=flags))
    assert m.transformer.is_gradient_checkpointing == flags
    assert offloaded == ([m.text_encoder, judge.model] if flags else [])
    seen = []

    def load_base(args):   # bench.py's loader call, stopped there with an error bench.py reports
        seen.append(args)
        raise ValueError("stop here")
    monkeypatch.setattr(train, "load_base", load_base)
    with pytest.raises(SystemExit):
        bench.main(["--model", "ltx2-tiny", "--judge", "qwen-vl-tiny"] + ["--offload_text", "--offload_judge"] * flags)
    assert (seen[0].offload_text, seen[0].offload_judge) == (flags, flags)


PARTS = {models.LTX2Video: ("LTX2ImageToVideoPipeline", {"max_sequence_length": 16}),
         models.HunyuanVideo15: ("HunyuanVideo15ImageToVideoPipeline",
                                 {"max_sequence_length": 16, "crop_start": 0, "byt5_max_length": 16})}


@pytest.mark.parametrize("cls", [models.LTX2Video, models.HunyuanVideo15])
def test_from_pretrained_loads_every_component_from_its_pipelines_folder(cls, tmp_path):
    """from_pretrained, the path real weights take (they cannot be downloaded here): a tiny model's components,
    saved each under the name diffusers' own image-to-video pipeline gives it (the folders of a snapshot), load back
    into the same model -- the same condition and velocity, bit for bit, in float32 -- given the tiny model's text
    settings (the defaults are the pipeline's: LTX-2 pads a prompt to 1024 tokens, and its connectors' registers
    make the velocity depend on that length)."""
    import diffusers
    pipeline, text = PARTS[cls]
    assert set(cls.PARTS) <= set(inspect.signature(getattr(diffusers, pipeline).__init__).parameters)
    m, f0, c_E, _ = _tiny(cls)
    missing = f"is not a diffusers .* directory: it has no folders {', '.join(cls.PARTS)} "
    with pytest.raises(FileNotFoundError, match=missing):
        cls.from_pretrained(str(tmp_path))          # a folder, but not the pipeline's: nothing loaded, one line
    for name in cls.PARTS:
        getattr(m, name).save_pretrained(str(tmp_path / name))
    loaded = cls.from_pretrained(str(tmp_path), frames=m.frames, height=m.height, width=m.width,
                                 dtype=torch.float32, **text)
    pairs = world.make_pairs(2, seed=0, error_rate=0.0)
    c = loaded.condition(f0, [p.task.text for p in pairs])
    assert c.keys() == c_E.keys() and all(torch.equal(c[k], c_E[k]) for k in c)
    x = torch.randn(2, *m.latent_shape(), generator=torch.Generator().manual_seed(0))
    t = torch.tensor([0.3, 0.6])
    with torch.no_grad():
        assert torch.equal(loaded(x, t, c), m(x, t, c_E))


def test_the_vlm_judge_loads_from_a_directory(tmp_path):
    """VLMJudge.from_pretrained (--judge qwen-vl --judge_path): a tiny judge's model, tokenizer and image processor
    saved to one directory load back into a judge with the same logits for the same videos and prompts."""
    judge = reward.VLMJudge.tiny(world.VOCAB + ["[", "]:"])
    with pytest.raises(FileNotFoundError, match="is not a transformers model directory: it has no config.json"):
        reward.VLMJudge.from_pretrained(str(tmp_path))
    for part in (judge.model, judge.tokenizer, judge.image_processor):
        part.save_pretrained(str(tmp_path))
    loaded = reward.VLMJudge.from_pretrained(str(tmp_path), frames=judge.frames, batch=judge.batch)
    pairs = world.make_pairs(3, seed=0, error_rate=0.0)
    videos = np.stack([world.render(p.scene, world.simulate(p.scene, p.plan_oracle)) for p in pairs])
    prompts = [reward.TASK_REWARD_PROMPT.format(instruction=p.task.text, agent_name=world.split_task(p.task.text)[0])
               for p in pairs]
    assert np.array_equal(loaded.logits(videos, prompts), judge.logits(videos, prompts))


@pytest.mark.parametrize("cls", [models.LTX2Video, models.HunyuanVideo15])
def test_lora_weights_train_in_float32_on_a_bfloat16_base(cls):
    """from_pretrained loads the real models in bfloat16, where a weight near 0.016 moves in steps of 1.2e-4 and an
    Adam step at Table 3's lr 2e-4 would be rounded away; the adapters are float32 and take the step whole."""
    m, f0, c_E, _ = _tiny(cls)
    m.transformer.to(torch.bfloat16)
    models.add_lora(m, 4, 8.0)
    lora = {n: p for n, p in m.transformer.named_parameters() if "lora_" in n}
    assert {p.dtype for p in lora.values()} == {torch.float32}
    assert {p.dtype for n, p in m.transformer.named_parameters() if n not in lora} == {torch.bfloat16}
    x = torch.randn(2, *m.latent_shape(), generator=torch.Generator().manual_seed(0))
    m(x, torch.tensor([0.3, 0.6]), c_E).pow(2).mean().backward()
    before = {n: p.detach().clone() for n, p in lora.items()}
    torch.optim.Adam(list(lora.values()), lr=2e-4).step()
    step = max((p.detach() - before[n]).abs().max().item() for n, p in lora.items())
    assert step == pytest.approx(2e-4, rel=0.01)                   # Adam's first step is lr, kept exactly


@pytest.mark.parametrize("cls", [models.LTX2Video, models.HunyuanVideo15])
def test_a_model_held_in_bfloat16_builds_samples_and_decodes(cls):
    """from_pretrained loads every component in bfloat16. Building such a model used to fail in __init__: the probe
    that reads the latent grid off the VAE sent it float32 zeros on the CPU ("Input type (float) and bias type
    (c10::BFloat16) should be the same"). The probe now uses the VAE's own device and dtype."""
    m = cls.tiny(world.VOCAB + ["[", "]:"], dtype=torch.bfloat16)
    assert {p.dtype for p in m.parameters()} == {torch.bfloat16}
    pairs = world.make_pairs(2, seed=0, error_rate=0.0)
    f0 = np.stack([p.frame0 for p in pairs])
    x = torch.randn(2, *m.latent_shape(), generator=torch.Generator().manual_seed(0))
    v = m(x, torch.tensor([0.3, 0.6]), m.condition(f0, [p.task.text for p in pairs]))
    assert v.shape == x.shape and v.dtype == torch.float32 and torch.isfinite(v).all()
    video = m.decode(x, f0)
    assert video.dtype == np.uint8 and video.shape[0] == 2 and video.shape[2:] == (m.height, m.width, 3)


@pytest.mark.parametrize("cls", [models.LTX2Video, models.HunyuanVideo15])
def test_an_offloaded_text_encoder_visits_for_each_encoding_and_gives_the_same_condition(cls):
    """--offload_text: the text encoder's weights live in CPU memory; for each condition() call they are copied to
    the transformer's device and afterwards are their CPU originals again (the same tensors, nothing copied back).
    Checked with a cast to float64 standing in for the copy to a GPU, which this machine lacks (Tensor.to takes
    either): inside the block every weight is a new tensor, after it every weight is the original. The condition is
    the same as without offloading. (That the copy goes to the GPU and saves its memory was measured on one: docs/real-models.md,
    a real-size step on a GPU.)"""
    m, f0, c_E, _ = _tiny(cls)
    models.offload(m.text_encoder)
    home = [(t.data_ptr(), t.dtype) for t in models._weights(m.text_encoder)]
    with models.visiting(m.text_encoder, torch.float64):
        assert {t.dtype for t in models._weights(m.text_encoder) if t.is_floating_point()} == {torch.float64}
    assert [(t.data_ptr(), t.dtype) for t in models._weights(m.text_encoder)] == home
    pairs = world.make_pairs(2, seed=0, error_rate=0.0)
    c = m.condition(f0, [p.task.text for p in pairs])
    assert [(t.data_ptr(), t.dtype) for t in models._weights(m.text_encoder)] == home
    assert c.keys() == c_E.keys() and all(torch.equal(c[k], c_E[k]) for k in c)


def test_ltx2_random_has_ltx2_19bs_sizes():
    """--model ltx2-random (a real-size step's seconds and memory on a GPU) builds LTX-2-19B's components: counted
    on the meta device, where nothing is allocated. The transformer 18.9B parameters (video and audio streams),
    Gemma-3-12B's text model 11.8B, the connectors 1.4B, the VAE 1.2B; at Table 3's 121 frames of 384 x 576 the
    state is 15 latent frames of 12 x 18 after the first (the VAE: 8x in time, 32x in space, 128 channels)."""
    m = models.LTX2Video.random(world.VOCAB + ["[", "]:"], device="meta")
    count = {k: sum(p.numel() for p in getattr(m, k).parameters()) / 1e9
             for k in ("transformer", "text_encoder", "connectors", "vae")}
    assert count == pytest.approx({"transformer": 18.88, "text_encoder": 11.77, "connectors": 1.43, "vae": 1.22},
                                  abs=0.01)
    assert m.latent_shape() == (128, 15, 12, 18)
    z = torch.empty(1, 128, 16, 12, 18, device="meta", dtype=torch.bfloat16)      # the first frame's latent and x_1's
    assert m.vae.decode(z, return_dict=False)[0].shape == (1, 3, 121, 384, 576)    # back to its 121 frames
    assert {p.dtype for p in m.parameters()} == {torch.bfloat16} and m.max_len == 1024
    assert torch.get_default_dtype() == torch.float32          # the build's bf16 default does not leak
    for script in ("train.py", "bench.py"):
        r = run(script, "--model", "ltx2-random")
        assert r.returncode == 2 and "needs a CUDA GPU" in r.stderr    # this machine has none


def test_hunyuan15_random_has_hunyuanvideo15_480ps_sizes():
    """--model hunyuan15-random builds HunyuanVideo-1.5 480p i2v's components, counted on the meta device: the
    transformer 8.33B parameters, Qwen2.5-VL-7B's text model 7.07B, ByT5-small's encoder 0.22B, SigLIP-so400m 0.43B,
    the VAE 1.26B; at Table 3's 121 frames of 480 x 848 the state is 31 latent frames of 30 x 53 with 32 channels
    (the VAE: 4x in time, 16x in space), 49,290 tokens."""
    m = models.HunyuanVideo15.random(world.VOCAB + ["[", "]:"], device="meta")
    count = {k: sum(p.numel() for p in getattr(m, k).parameters()) / 1e9
             for k in ("transformer", "text_encoder", "text_encoder_2", "image_encoder", "vae")}
    assert count == pytest.approx({"transformer": 8.33, "text_encoder": 7.07, "text_encoder_2": 0.22,
                                   "image_encoder": 0.43, "vae": 1.26}, abs=0.005)
    assert m.latent_shape() == (32, 31, 30, 53) and 31 * 30 * 53 == 49290
    assert {p.dtype for p in m.parameters()} == {torch.bfloat16} and torch.get_default_dtype() == torch.float32
    for script in ("train.py", "bench.py"):
        r = run(script, "--model", "hunyuan15-random")
        assert r.returncode == 2 and "needs a CUDA GPU" in r.stderr    # this machine has none


@pytest.mark.parametrize("name", ["ltx", "hy"])
def test_a_tiny_model_decodes_its_state_into_videos_of_its_frame_count(name, request):
    """decode(x_1) of a tiny backend is a video of model.frames frames, the count the +SFT videos are held to, as at
    the real sizes (test_ltx2_random_has_ltx2_19bs_sizes decodes LTX-2's 121). The tiny LTX-2 made 9 of 5 with
    diffusers' test VAE, whose encoder halved space but not time (stop 118)."""
    m, f0, _, _ = request.getfixturevalue(name)
    video = m.decode(torch.randn(len(f0), *m.latent_shape(), generator=torch.Generator().manual_seed(0)), f0)
    assert video.shape == (len(f0), m.frames, m.height, m.width, 3) and m.frames == 5


@pytest.mark.parametrize("cls", [models.LTX2Video, models.HunyuanVideo15])
def test_gradient_checkpointing_recomputes_and_gives_the_same_gradients(cls):
    """train.py --grad_checkpoint: the transformer's blocks run again in the backward pass instead of keeping their
    activations, and the LoRA gradients of Eq. 12's anchor are the same."""
    m, f0, c_E, c_D = _tiny(cls)
    models.add_lora(m, 4, 8.0)
    for n, p in m.named_parameters():   # B != 0: the Executor differs from the Demonstrator, the anchor has a gradient
        if "lora_B" in n:
            p.data.normal_(0, 0.1, generator=torch.Generator().manual_seed(0))
    calls, block = [], m.transformer.transformer_blocks[0]
    forward = block.forward      # counted by wrapping forward: the recomputation does not run forward hooks
    block.forward = lambda *a, **k: calls.append(1) or forward(*a, **k)
    x0 = torch.randn(2, *m.latent_shape(), generator=torch.Generator().manual_seed(0))

    def grads():
        m.zero_grad()
        calls.clear()
        distill.anchor_loss(m, distill.rollout(m, x0, c_E, 2), c_E, c_D, torch.Generator().manual_seed(0)).backward()
        return [p.grad.clone() for p in models.lora_parameters(m)], len(calls)

    plain, n_plain = grads()
    m.transformer.enable_gradient_checkpointing()
    ckpt, n_ckpt = grads()
    assert n_ckpt == n_plain + 1                           # the anchor's one forward with gradient, run again
    assert any(g.abs().max() > 0 for g in plain)
    assert all(torch.allclose(a, b, atol=1e-6, rtol=1e-5) for a, b in zip(plain, ckpt))


def test_a_prompt_longer_than_ltx2s_text_path_is_an_error_not_cut(ltx, tmp_path):
    """LTX-2's text path pads to max_sequence_length tokens (1024 as diffusers' pipelines; the tiny model 16); a
    longer D used to be cut silently. Now condition() refuses it, and train.py names the dataset line up front."""
    m, f0, _, _ = ltx
    long = " ".join(["red square moves right 1"] * 5)
    with pytest.raises(ValueError, match=r"has \d+ tokens; LTX-2's text path takes at most 16"):
        m.condition(f0[:1], [long])
    words = long.split()
    assert len(m.tokenizer(" ".join(words[:16])).input_ids) == 16
    assert m.condition(f0[:1], [" ".join(words[:16])])["mask"].shape[0] == 1   # exactly 16 tokens: taken whole
    with pytest.raises(ValueError, match="has 17 tokens"):
        m.check_prompts([" ".join(words[:17])])
    data = _toy_dataset(tmp_path / "data", 2)
    row = json.loads(open(data).readline())
    with open(data, "a") as f:
        f.write(json.dumps({**row, "description": long}) + "\n")
    r = run("train.py", "--model", "ltx2-tiny", "--dataset", data, "--steps", "1", "--run_dir", str(tmp_path / "r"))
    assert r.returncode == 2 and "data.jsonl line 3" in r.stderr and "at most 16" in r.stderr, r.stderr[-500:]
    assert "Traceback" not in r.stderr and not (tmp_path / "r").exists()


def test_a_prompt_longer_than_hunyuanvideo15s_text_path_is_an_error_not_cut(hy, tmp_path):
    """HunyuanVideo-1.5's pipeline encoding pads the chat-formatted prompt to max_sequence_length tokens past the
    cropped system turn (1000; the tiny model 16) and cut a longer one silently, as LTX-2's did. condition() refuses
    it, and train.dataset_pairs names the dataset line."""
    import train
    m, f0, _, _ = hy
    words = "red square moves right 1".split()
    with pytest.raises(ValueError, match=r"has 25 tokens; HunyuanVideo-1.5's text path takes at most 16"):
        m.condition(f0[:1], [" ".join(words * 5)])
    m.check_prompts([" ".join(words * 3), ""])          # 15 words, and an empty prompt: taken whole
    data = _toy_dataset(tmp_path / "data", 2)
    row = json.loads(open(data).readline())
    with open(data, "a") as f:
        f.write(json.dumps({**row, "description": " ".join(words * 5)}) + "\n")
    with pytest.raises(ValueError, match=r"data.jsonl line 3: .*at most 16"):
        train.dataset_pairs(data, m, 2, "--tasks_per_step")


@pytest.mark.parametrize("cls", [models.LTX2Video, models.HunyuanVideo15])
def test_alg2s_demonstrator_shares_the_base_and_owns_its_lora(cls):
    """train.py --alternate: phi is a second network over the same base tensors (weights and buffers, the
    transformer's and the frozen VAE's and encoders'), so a real run holds the base once, with a LoRA of its own:
    training phi's LoRA leaves the Executor as it was, the Executor's leaves phi, and phi's adapters off is the base."""
    m, f0, c_E, _ = _tiny(cls)
    phi = models.copy_for_adapter(m)
    tensors = lambda net: {t.data_ptr() for n, t in (*net.named_parameters(), *net.named_buffers()) if "lora_" not in n}
    assert phi.transformer is not m.transformer and tensors(phi) == tensors(m)
    x = torch.randn(2, *m.latent_shape(), generator=torch.Generator().manual_seed(0))
    t = torch.tensor([0.3, 0.6])
    with torch.no_grad():
        base = m(x, t, c_E)
    models.add_lora(phi, 4, 8.0)
    models.add_lora(m, 4, 8.0)
    lora_phi, lora_m = models.lora_parameters(phi), models.lora_parameters(m)
    assert lora_phi and lora_m and not {p.data_ptr() for p in lora_phi} & {p.data_ptr() for p in lora_m}
    assert tensors(phi) == tensors(m)       # adding the adapters copied no base weight
    for p in lora_phi:
        p.data.normal_(0, 0.1)
    with torch.no_grad():
        v_phi = phi(x, t, c_E)
        assert torch.equal(m(x, t, c_E), base) and not torch.allclose(v_phi, base)
    for p in lora_m:
        p.data.normal_(0, 0.1)
    with torch.no_grad():
        assert not torch.allclose(m(x, t, c_E), base) and torch.equal(phi(x, t, c_E), v_phi)
        with models.adapters_disabled(phi):
            assert torch.equal(phi(x, t, c_E), base)
    with pytest.raises(ValueError, match="before adding adapters"):
        models.copy_for_adapter(m)


@pytest.mark.parametrize("cls", [models.LTX2Video, models.HunyuanVideo15])
def test_a_repeated_image_and_prompt_is_encoded_once(cls, monkeypatch):
    """models.distinct_condition: the text encoders and the VAE see each distinct (first frame, prompt) once, and
    the rows it hands back are condition()'s for the whole batch. Rows 0 and 4 share a frame, not a prompt."""
    m, f0, _, _ = _tiny(cls)
    texts = ["[red square]: move right", "[blue circle]: move up"]
    rows = [0, 0, 1, 0, 0, 1, 1]
    frames, prompts = f0[rows], [texts[i] for i in rows]
    prompts[4] = texts[1]
    want = m.condition(frames, prompts)
    seen, condition = [], m.condition
    monkeypatch.setattr(m, "condition", lambda f, t: seen.append(list(t)) or condition(f, t))
    c, index = models.distinct_condition(m, frames, prompts)
    assert seen == [[texts[0], texts[1], texts[1]]] and index.tolist() == [0, 0, 1, 0, 2, 1, 1]
    got = models.condition_rows(c, index)
    assert got.keys() == want.keys()
    for k in want:
        assert torch.allclose(got[k].float(), want[k].float(), atol=1e-5), k


def test_missing_packages_and_weights_give_clear_errors(tmp_path):
    with pytest.raises(ImportError, match="no_such_package"):
        models._require("no_such_package")
    r = run("train.py", "--model", "ltx2")
    assert r.returncode == 2 and "--model ltx2 needs --model_path" in r.stderr
    r = run("train.py", "--model", "ltx2", "--model_path", str(tmp_path / "nowhere"), "--run_dir", str(tmp_path / "r"))
    assert r.returncode == 2 and "LTX-2 weights not found" in r.stderr and "Traceback" not in r.stderr
    r = run("train.py", "--model", "hunyuan15")
    assert r.returncode == 2 and "--model hunyuan15 needs --model_path" in r.stderr
    r = run("train.py", "--model", "hunyuan15", "--model_path", str(tmp_path / "nowhere"),
            "--run_dir", str(tmp_path / "r"))
    assert r.returncode == 2 and "HunyuanVideo-1.5 weights not found" in r.stderr and "Traceback" not in r.stderr
    r = run("train.py", "--judge", "qwen-vl", "--judge_path", str(tmp_path / "nowhere"),
            "--run_dir", str(tmp_path / "r"))
    assert r.returncode == 2 and "VLM weights not found" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize("model,judge,extra", [
    ("ltx2-tiny", "qwen-vl-tiny", ["--micro_batch", "1", "--grad_checkpoint", "--offload_text", "--offload_judge"]),
    ("hunyuan15-tiny", "qwen-vl-tiny", ["--eval_dataset", "held"]),
    ("ltx2-tiny", "toy", [])])
def test_one_wmsd_run_on_a_tiny_real_model(model, judge, extra, tmp_path):
    """Alg. 1 with the real classes on a WorldTasks JSONL file: LTX-2 (or HunyuanVideo-1.5) rollouts, Qwen3-VL
    judgments (random weights answer with arbitrary tokens: malformed, counted, skipped), r_distill, advantages,
    AWM + anchor, evaluation, the LoRA file; LTX-2 one rollout per pass with gradient checkpointing, as at real size,
    and HunyuanVideo-1.5 evaluated on a held-out WorldTasks file. With the toy judges, which read LTX-2's 32x32 toy
    world block-averaged to its 16x16, every rollout is judged."""
    data = _toy_dataset(tmp_path / "data", 2)
    extra = [_toy_dataset(tmp_path / "held", 2, seed=6) if a == "held" else a for a in extra]
    r = run("train.py", "--model", model, "--judge", judge, "--dataset", data, "--steps", "1", *extra,
            "--group_size", "2", "--tasks_per_step", "1", "--eval_every", "1", "--eval_n", "2", "--sample_steps", "2",
            "--run_dir", str(tmp_path))
    assert r.returncode == 0, r.stderr[-2000:]
    assert "| WMSD (awm, T)" in r.stdout
    assert ("evaluated on the toy bench" in r.stdout) == ("--eval_dataset" not in extra)
    assert ("(Demonstrator, the bench file's D)" in r.stdout) == ("--eval_dataset" in extra)
    assert set(torch.load(tmp_path / "executor_awm.pt", weights_only=True)["lora"]) and (tmp_path / "state.pt").exists()
    step = [json.loads(line) for line in open(tmp_path / "rl.jsonl") if '"A"' in line][0]
    assert step["invalid"] + sum(1 for a in step["A"] if a != 0) >= 1 and step["r_distill"] < 0
    assert judge != "toy" or (step["invalid"] == 0 and all(a != 0 for a in step["A"]))
    assert "rollout videos, the Demonstrator beside the Executor" in r.stdout
    assert (tmp_path / "rollouts_rl.gif").exists() and (tmp_path / "rollouts_rl" / "001.mp4").exists()
    if model == "ltx2-tiny" and judge != "toy":   # the saved Executor, benched on a held-out WorldTasks file
        lora, held = str(tmp_path / "executor_awm.pt"), _toy_dataset(tmp_path / "bench", 2, seed=7)
        m = models.LTX2Video.tiny(world.VOCAB + ["[", "]:"])
        models.load_lora(m, lora, add=True)                 # adapters of the run's rank, then its weights
        saved = torch.load(lora, weights_only=True)["lora"]
        assert all(torch.equal(m.state_dict()[k], v) for k, v in saved.items())
        r = run("bench.py", "--model", model, "--lora", lora, "--judge", judge, "--dataset", held, "--n", "2",
                "--steps", "2", "--batch", "1", "--guidance", "2", "--png", str(tmp_path / "b.png"),
                "--videos", str(tmp_path / "vid"))
        assert r.returncode == 0, r.stderr[-2000:]        # guided: the empty caption through Gemma and connectors
        assert f"model={model} + {lora} judge={judge} bench={held}" in r.stdout and "| task " in r.stdout
        assert "steps=2 guidance=2" in r.stdout
        assert f"Executor: {lora}, {len(saved)} LoRA weights loaded (rank 8, 1 steps of --model {model})" in r.stdout
        assert (tmp_path / "b.png").exists()
        assert [json.loads(line)["video"] for line in open(tmp_path / "vid" / "videos.jsonl")] == ["000.mp4", "001.mp4"]
        assert world.load_video(str(tmp_path / "vid" / "001.mp4")).shape == (m.frames, m.height, m.width, 3)
        import bench
        import train
        assert set(bench.REAL_MODELS) == set(train.REAL_MODELS)   # bench.py offers what train.py loads
        (tmp_path / "bad.pt").write_bytes(b"garbage")
        for argv, msg in ((["--lora", str(tmp_path / "bad.pt")], "corrupt"),
                          (["--lora", lora, "--model", "toy"], "--lora loads a real model's Executor"),
                          (["--condition", "oracle"], "a --dataset bench has"),
                          (["--compare", "x=runs"], "are toy diagnostics")):
            r = run("bench.py", "--model", model, "--dataset", held, "--n", "2", *argv)
            assert r.returncode == 2 and msg in r.stderr and "Traceback" not in r.stderr, (argv, r.stderr[-500:])


def test_tiny_vlm_judge_batches_like_single_items():
    judge = reward.VLMJudge.tiny(world.VOCAB + ["[", "]:"])
    pairs = world.make_pairs(3, seed=1, error_rate=0.0)
    videos = [np.repeat(p.frame0[None], 6, axis=0) for p in pairs]
    tasks = [p.task.text for p in pairs]
    prompts = [reward.TASK_REWARD_PROMPT.format(instruction=t, agent_name=world.parse_task(t).agent) for t in tasks]
    assert len({len(p.split()) for p in prompts}) > 1                      # different lengths: left padding is used
    assert prompts[0].startswith(f"Instruction: {tasks[0]} Target agent: {world.split_task(tasks[0])[0]} You are")
    assert reward.BENCH_AGENT_PROMPT.format(eval_prompt="[a b]: go", agent_name="a b", agent_task_text="go").startswith(
        "Full instruction: [a b]: go Expected acting agent: a b Expected task for that agent: go")
    inner, seen = judge.model.model, []
    rope_index = inner.get_rope_index

    def rope(ids, **k):        # the M-RoPE positions (time, height, width) the model makes of the judge's inputs
        out = rope_index(ids, **k)
        seen.append((ids, out[0]))
        return out
    inner.get_rope_index = rope
    judge.logits([np.zeros((2, 64, 64, 3), np.uint8)], prompts[:1])   # 64 px: 2 x 2 tokens a frame
    del inner.get_rope_index
    ids, pos = seen[0]
    image = ids == judge.ids["<|image_pad|>"]
    assert image.any() and (pos[1][image] != pos[2][image]).any()   # each frame's tokens on a 2-D grid of positions,
    assert (pos[0][~image] == pos[1][~image]).all() and (pos[1][~image] == pos[2][~image]).all()   # text on a line
    batched = judge.logits(videos, prompts)
    for i in range(3):
        assert np.allclose(batched[i], judge.logits(videos[i:i + 1], prompts[i:i + 1])[0], atol=1e-4)
    forward = judge.model.forward      # the head on every position, as before logits_to_keep=1: the same last logits
    judge.model.forward = lambda *a, logits_to_keep=0, **k: forward(*a, **k)
    assert np.allclose(batched, judge.logits(videos, prompts), atol=1e-5)
    del judge.model.forward
    out = judge.task_reward(videos, tasks)
    assert len(out) == 3 and all(isinstance(j, reward.Judgment) for j in out)
    assert len(judge.bench(videos[:1], tasks[:1])[0]) == 3
    r = run("train.py", "--judge", "qwen-vl")
    assert r.returncode == 2 and "--judge qwen-vl needs --judge_path" in r.stderr


def test_the_vlm_judges_frames_prompts_and_answer_tokens():
    """What VLMJudge asks and reads, with its logits stubbed (random weights answer nothing): the frames it shows
    are spread evenly from the first to the last; the training rewards ask Figs. 10-11's prompts and read "Yes" /
    "No" (as the suitability filter's question, Fig. 12), the bench asks Figs. 15-17's with the agent and its task
    in their places and reads "1" / "0"."""
    judge = reward.VLMJudge.tiny(world.VOCAB + ["[", "]:"])
    video = np.arange(6)[:, None, None, None].repeat(8, 1).repeat(8, 2).repeat(3, 3).astype(np.uint8) * 10
    assert [np.asarray(im)[0, 0, 0] for im in judge._frames(video)] == [0, 20, 30, 50]     # 4 of 6 frames
    asked, likely = [], ["Yes"]

    def logits(videos, prompts):   # the likely token 5 above the rest: a reader of the wrong pair flips or fails
        asked.extend(prompts)
        out = np.zeros((len(prompts), len(judge.tokenizer.get_vocab())), np.float32)
        out[:, judge.ids[likely[0]]] = 5.0
        return out
    judge.logits = logits
    task = "[red square]: move right"
    assert judge.task_reward([video], [task])[0].yes is True
    assert asked.pop() == reward.TASK_REWARD_PROMPT.format(instruction=task, agent_name="red square")
    assert judge.consistency_reward([video])[0].yes is True and asked.pop() == reward.CONSISTENCY_REWARD_PROMPT
    assert judge.yes_no([video[0]], world.SUITABILITY_PROMPT) == [True] and asked.pop() == world.SUITABILITY_PROMPT
    likely[0] = "0"
    verdicts = judge.bench([video], [task])[0]
    assert [verdicts[k].yes for k in ("task", "agent", "consistency")] == [False] * 3
    assert asked[-3:] == [reward.BENCH_TASK_PROMPT.format(eval_prompt=task),
                          reward.BENCH_AGENT_PROMPT.format(eval_prompt=task, agent_name="red square",
                                                           agent_task_text="move right"),
                          reward.BENCH_CONSISTENCY_PROMPT]
    # an answer word the tokenizer splits into pieces has no single logit to read: refused when the judge is built
    vocab = {k: v for k, v in judge.tokenizer.get_vocab().items() if k != "Yes"}
    with pytest.raises(ValueError, match="no single token 'Yes'"):
        reward.VLMJudge(judge.model, SimpleNamespace(get_vocab=lambda: vocab), judge.image_processor)


def test_an_offloaded_judge_visits_for_each_batch_and_gives_the_same_logits():
    """--offload_judge: the VLM's weights live in CPU memory and visit the judge's device for each call that judges,
    then are their CPU originals again. As for the text encoder, a cast to float64 stands in for the copy to a GPU:
    inside the forward every weight is a new float64 tensor, after it the original; the logits are the resident
    judge's (to float32's precision)."""
    judge = reward.VLMJudge.tiny(world.VOCAB + ["[", "]:"])
    pairs = world.make_pairs(3, seed=1, error_rate=0.0)
    videos = [np.repeat(p.frame0[None], 6, axis=0) for p in pairs]
    prompts = [reward.CONSISTENCY_REWARD_PROMPT] * 3
    resident = judge.logits(videos, prompts)
    judge.offload()
    judge.device = torch.float64
    home = [(t.data_ptr(), t.dtype) for t in models._weights(judge.model)]
    seen = []
    hook = judge.model.register_forward_pre_hook(
        lambda mod, args: seen.append({(t.data_ptr(), t.dtype) for t in models._weights(mod)}))
    offloaded = judge.logits(videos, prompts)
    hook.remove()
    assert len(seen) == 1 and not seen[0] & set(home) and {d for _, d in seen[0]} >= {torch.float64}
    assert [(t.data_ptr(), t.dtype) for t in models._weights(judge.model)] == home
    assert np.allclose(offloaded, resident, atol=1e-4) and not np.array_equal(offloaded, resident)
    for script in ("train.py", "bench.py"):
        r = run(script, "--offload_judge")
        assert r.returncode == 2 and "--offload_judge is for a VLM judge" in r.stderr


def test_qwen_vl_random_has_qwen3_vl_8bs_sizes():
    """--judge qwen-vl-random (a real-size judgment's seconds and memory on a GPU) builds Qwen3-VL-8B-Instruct:
    counted on the meta device, 8.77B parameters (vision 0.58B, language model 7.57B, untied output head 0.62B), in
    bf16; its image processor makes a 384 x 576 frame 24 x 36 patches of 16 px, merged 2 x 2 into 216 tokens."""
    judge = reward.VLMJudge.random(world.VOCAB + ["[", "]:"], device="meta")
    m = judge.model
    count = {k: sum(p.numel() for p in mod.parameters()) / 1e9
             for k, mod in (("all", m), ("vision", m.model.visual), ("language", m.model.language_model),
                            ("head", m.lm_head))}
    assert count == pytest.approx({"all": 8.77, "vision": 0.58, "language": 7.57, "head": 0.62}, abs=0.005)
    assert {p.dtype for p in m.parameters()} == {torch.bfloat16} and torch.get_default_dtype() == torch.float32
    frame = np.zeros((384, 576, 3), np.uint8)
    grid = judge.image_processor(images=[Image.fromarray(frame)], return_tensors="pt")["image_grid_thw"]
    assert grid.tolist() == [[1, 24, 36]] and int(grid.prod()) // 4 == 216
    for script in ("train.py", "bench.py"):
        r = run(script, "--judge", "qwen-vl-random")
        assert r.returncode == 2 and "needs a CUDA GPU" in r.stderr    # this machine has none


def _toy_dataset(d, n, seed=5):
    """A WorldTasks-format JSONL over toy first frames saved as PNGs (what world.make_worldtasks writes)."""
    from PIL import Image
    d.mkdir(parents=True, exist_ok=True)
    rows = []
    for i, p in enumerate(world.make_pairs(n, seed=seed, error_rate=0.0)):
        Image.fromarray(p.frame0).resize((32, 32), Image.NEAREST).save(d / f"{i}.png")
        rows.append({"image": f"{i}.png", "task": p.task.text, "description": p.d_oracle,
                     "agent": world.split_task(p.task.text)[0], "family": p.task.family})
    (d / "data.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    return str(d / "data.jsonl")


def test_image_quality_filter_uses_the_papers_thresholds():
    rng = np.random.default_rng(0)
    checker = (np.indices((64, 64)).sum(0) % 2 * 200 + 30).astype(np.uint8)[..., None].repeat(3, -1)
    assert world.quality_ok(checker) == (True, "")
    assert world.quality_ok(np.full((64, 64, 3), 128, np.uint8)) == (False, "blurry")        # Laplacian variance 0
    noisy_dark = rng.integers(0, 30, (64, 64, 3)).astype(np.uint8)
    assert world.quality_ok(noisy_dark)[1] in ("underexposed", "mostly black")
    noisy_bright = rng.integers(235, 256, (64, 64, 3)).astype(np.uint8)
    assert world.quality_ok(noisy_bright)[1] in ("overexposed", "mostly white")
    q = world.image_quality(checker)
    assert q["black_ratio"] == 0 and abs(q["mean_luma"] - 130) < 1e-6


def test_task_solution_parsing_and_the_dataset_file(tmp_path):
    answer = ("1. Task 1: [Driver in racing suit]: Press the red button on the steering wheel.\n"
              "Description 1: The driver's right hand moves slightly forward and presses the red button.\n"
              "2. Task 2: no brackets here\nDescription 2: dropped\n"
              "3. Task 3: [First-person view]: Align the bumper with the curb. Description 3: The car drifts left.\n"
              "4. Task 4: [ ]: Wave.\nDescription 4: dropped: brackets, but no agent in them")
    pairs = world.parse_task_solutions(answer)
    assert [t for t, _ in pairs] == ["[Driver in racing suit]: Press the red button on the steering wheel.",
                                     "[First-person view]: Align the bumper with the curb."]
    assert pairs[1][1] == "The car drifts left."

    class FakeVLM:      # keeps the first image, answers with the text above
        def yes_no(self, images, prompt):
            assert prompt == world.SUITABILITY_PROMPT
            return [i == 0 for i in range(len(images))]

        def generate(self, images, prompt):
            return [answer] * len(images)

        def choose(self, prompts, n):
            return [0] * len(prompts)

    from PIL import Image
    checker = (np.indices((64, 64)).sum(0) % 2 * 200 + 30).astype(np.uint8)[..., None].repeat(3, -1)
    paths = []
    for i, img in enumerate([checker, checker, np.zeros((64, 64, 3), np.uint8)]):
        Image.fromarray(img).save(tmp_path / f"{i}.png")
        paths.append(str(tmp_path / f"{i}.png"))
    (tmp_path / "cut.png").write_bytes((tmp_path / "0.png").read_bytes()[:100])     # an image file cut short
    counts = world.make_worldtasks(paths + [str(tmp_path / "cut.png")], FakeVLM(), str(tmp_path / "wt.jsonl"),
                                   per_image=8)
    assert counts["pairs"] == 2 and counts["kept_images"] == 1 and counts["unsuitable"] == 1
    assert counts["unreadable"] == 1 and counts["images"] == 4
    assert counts.get("underexposed", 0) + counts.get("blurry", 0) == 1
    rows = world.load_dataset(str(tmp_path / "wt.jsonl"))
    assert rows[0]["agent"] == "Driver in racing suit" and rows[1]["family"] == "positioning"
    assert [(r["agent_type"], r["task_type"]) for r in rows] == [("first-person view", "positioning")] * 2
    # a bad line: one clear error naming the file and line, from the loader and from train.py
    lines = (tmp_path / "wt.jsonl").read_text().splitlines()
    (tmp_path / "bad.jsonl").write_text(lines[0] + "\n" + '{"image": "0.png", "task": "press it"}' + "\n")
    with pytest.raises(ValueError, match=r"bad.jsonl line 2: missing or empty description"):
        world.load_dataset(str(tmp_path / "bad.jsonl"))
    r = run("train.py", "--model", "ltx2-tiny", "--dataset", str(tmp_path / "bad.jsonl"), "--run_dir",
            str(tmp_path / "never"))
    assert r.returncode == 2 and "line 2" in r.stderr and not (tmp_path / "never").exists()
    (tmp_path / "cut.jsonl").write_text(lines[0] + "\n" + lines[0].replace('"0.png"', '"cut.png"') + "\n")
    assert '"cut.png"' in (tmp_path / "cut.jsonl").read_text()
    r = run("bench.py", "--model", "ltx2-tiny", "--dataset", str(tmp_path / "cut.jsonl"), "--n", "2")
    assert r.returncode == 2 and "cut.jsonl line 2:" in r.stderr and "Traceback" not in r.stderr, r.stderr
    # the tiny VLM's own generate and yes/no run (random weights: arbitrary text)
    judge = reward.VLMJudge.tiny(["press"])
    assert isinstance(judge.generate([checker], "Propose tasks", max_new_tokens=3)[0], str)
    assert len(judge.yes_no([checker, checker], world.SUITABILITY_PROMPT)) == 2


def test_the_prompt_only_taxonomy_labels_rows_and_groups_fig_3_and_fig_7(tmp_path):
    """Sec. 4.1.2: make_worldtasks labels each row's agent and task type by asking the VLM T alone, a numbered list of
    the paper's categories; a malformed answer is kept as null and counted. Fig. 3 (dataset_composition) and Fig. 7
    (train.task_groups -> bench's subgroups) then count the paper's categories; a file without them keeps the
    bracket names and keywords. VLMJudge.choose reads the first answer token as an option's number."""
    tasks = ["[First-person view]: Turn left to face the door.", "[Red car]: Park beside the curb.",
             "[Knight]: Strike the dragon."]

    class VLM:      # keeps every image; answers by the agent in the prompt's task; two answers malformed
        asked = []      # every prompt choose was given

        def yes_no(self, images, prompt):
            return [True] * len(images)

        def generate(self, images, prompt):
            return ["".join(f"{k}. Task {k}: {t}\nDescription {k}: it happens.\n" for k, t in enumerate(tasks, 1))]

        def choose(self, prompts, n):
            self.asked += prompts
            out = []
            for p in prompts:
                task = p.split("Task: ")[1].split("\n")[0]
                if n == len(world.AGENT_TAXONOMY):
                    out.append({"F": 0, "R": 2}.get(task[1]))           # the knight: malformed
                else:
                    out.append({"F": 3, "K": 4}.get(task[1]))            # the car: malformed
            return out

    checker = (np.indices((64, 64)).sum(0) % 2 * 200 + 30).astype(np.uint8)[..., None].repeat(3, -1)
    Image.fromarray(checker).save(tmp_path / "0.png")
    vlm = VLM()
    counts = world.make_worldtasks([str(tmp_path / "0.png")], vlm, str(tmp_path / "wt.jsonl"))
    assert counts["pairs"] == 3 and counts["taxonomy malformed"] == 2
    assert len(vlm.asked) == 6 and "Task: [Red car]: Park beside the curb.\n" in vlm.asked[1]
    assert "\n1. first-person view\n2. human character\n" in vlm.asked[0] and "\n9. other\n" in vlm.asked[5]
    rows = world.load_dataset(str(tmp_path / "wt.jsonl"))
    assert [(r["agent_type"], r["task_type"]) for r in rows] == [
        ("first-person view", "perception"), ("vehicle", None), (None, "combat action")]
    comp = world.dataset_composition({"train": rows})["train"]
    assert list(comp["agent"]) == [*world.AGENT_TAXONOMY, "unclassified"]
    assert comp["agent"]["vehicle"] == 1 and comp["agent"]["unclassified"] == 1 and sum(comp["agent"].values()) == 3
    assert comp["task"]["combat action"] == 1 and comp["task"]["unclassified"] == 1 and sum(comp["task"].values()) == 3
    groups = [train.task_groups(r) for r in rows]
    assert [(g["family"], g["agent_type"]) for g in groups] == [
        ("perception", "first-person view"), ("unclassified", "vehicle"), ("combat action", "unclassified")]
    pairs = [SimpleNamespace(task=SimpleNamespace(**g)) for g in groups]
    yes = [{"task": reward.Judgment(k != 1, 0.0, ""), "agent": reward.Judgment(k == 1, 0.0, "")} for k in range(3)]
    import bench
    assert bench.agent_type_scores(pairs, yes) == {"first-person view": [0, 1], "unclassified": [0, 1],
                                                   "vehicle": [1, 1]}
    assert bench.family_scores(pairs, yes) == {"combat action": [1, 1], "perception": [1, 1], "unclassified": [0, 1]}
    # without the taxonomy: the bracket names and the keyword families, as before
    plain = [{k: v for k, v in r.items() if k not in ("agent_type", "task_type")} for r in rows]
    assert "red car" in world.dataset_composition({"train": plain})["train"]["agent"]
    assert train.task_groups(plain[1])["agent_type"] is None
    # a category not in the taxonomy (here a task type given as the agent's): one error naming the line
    lines = (tmp_path / "wt.jsonl").read_text().splitlines()
    (tmp_path / "bad.jsonl").write_text(lines[0] + "\n" + lines[1].replace('"vehicle"', '"navigation"') + "\n")
    with pytest.raises(ValueError, match=r"bad.jsonl line 2: agent_type 'navigation' is not one of"):
        world.load_dataset(str(tmp_path / "bad.jsonl"))
    # the VLM's side: the first answer token as a number, text only (the tiny Qwen3-VL's forward without an image)
    judge = reward.VLMJudge.tiny([])
    lg = judge.logits(None, [world.taxonomy_prompt(t, "agent_type") for t in tasks])
    assert lg.shape == (3, len(judge.tokenizer.get_vocab())) and np.isfinite(lg).all()
    vocab = judge.tokenizer.get_vocab()
    crafted = np.zeros((3, len(vocab)))
    crafted[0, vocab["3"]], crafted[1, vocab["Yes"]], crafted[2, vocab["7"]] = 1, 1, 1
    judge.logits = lambda videos, prompts: crafted
    assert judge.choose(["a", "b", "c"], 7) == [2, None, 6] and judge.choose(["a", "b", "c"], 6) == [2, None, None]
    with pytest.raises(ValueError, match="1 to 9"):
        judge.choose(["a"], 10)


def test_pickscore_scores_a_video_by_its_frames_and_is_table_3s_third_reward(tiny_ckpt, tmp_path):
    """reward.PickScore: exp(logit_scale) cos(E_image, E_text), averaged over a video's frames read, checked against
    CLIPModel's own feature functions; the same scores batched or one at a time; weights from local directories, a
    clear error where there are none. In train.py it is Table 3's third reward: a run that weighs PickScore alone
    (every other weight 0) learns from it, and logs it and each evaluation's mean."""
    import torch.nn.functional as F
    pick = reward.PickScore.tiny(world.VOCAB + ["[", "]:"])
    pairs = world.make_pairs(3, seed=1, error_rate=0.0)
    videos = np.stack([world.render(p.scene, world.simulate(p.scene, p.plan_oracle)) for p in pairs])
    tasks = [p.task.text for p in pairs]
    s = pick(videos, tasks)
    m = pick.model
    with torch.no_grad():
        e_t = m.get_text_features(**pick.tokenizer(tasks, padding=True, return_tensors="pt")).pooler_output
        frames = [f for v in videos for f in reward.video_frames(v, 2)]      # the tiny reads 2: the first and last
        pix = pick.image_processor(images=frames, return_tensors="pt").pixel_values
        e_i = m.get_image_features(pixel_values=pix).pooler_output
    cos = (F.normalize(e_i, dim=-1).view(3, 2, -1) * F.normalize(e_t, dim=-1)[:, None]).sum(-1)
    assert np.allclose(s, (m.logit_scale.exp() * cos.mean(1)).detach().numpy(), atol=1e-5)
    assert np.allclose(np.concatenate([pick(videos[i:i + 1], tasks[i:i + 1]) for i in range(3)]), s, atol=1e-5)
    assert not np.allclose(pick(videos, tasks[::-1]), s, atol=1e-3)          # the prompt counts
    still = videos.copy()
    still[:, -1] = videos[:, 0]
    assert not np.allclose(pick(still, tasks), s, atol=1e-3)                 # and so does the last frame
    m.save_pretrained(tmp_path / "pick")
    pick.tokenizer.save_pretrained(tmp_path / "proc")
    pick.image_processor.save_pretrained(tmp_path / "proc")
    assert np.allclose(reward.PickScore.from_pretrained(str(tmp_path / "pick"), str(tmp_path / "proc"), frames=2)(
        videos, tasks), s, atol=1e-5)
    with pytest.raises(FileNotFoundError, match="PickScore model not found at"):
        reward.PickScore.from_pretrained(str(tmp_path / "nothing"))
    with pytest.raises(FileNotFoundError, match="PickScore processor not found at"):
        reward.PickScore.from_pretrained(str(tmp_path / "pick"))          # no processor beside the model
    # the step's rewards: PickScore of each rollout against its T; one that fails is counted and skipped
    train.PICK = pick
    try:
        judged = train.judge_rollouts(videos, tasks, pick=train.weighed_pick(train.Args(pick="pickscore-tiny",
                                                                                        lambda_pick=0.2)))
        assert np.allclose(judged["pick"].numpy(), s, atol=1e-5) and not judged["invalid"].any()
        assert train.weighed_pick(train.Args(pick="pickscore-tiny")) is None     # --lambda_pick 0: a measure only

        def broken(videos, prompts):
            raise RuntimeError("out of memory")
        judged = train.judge_rollouts(videos, tasks, pick=broken)
        assert judged["invalid"].all() and judged["judge_errors"].tolist() == [1, 1, 1]
    finally:
        train.PICK = None
    d = tmp_path / "run"
    r = run("train.py", "--toy", "--init", tiny_ckpt, "--steps", "2", "--eval_every", "1", "--eval_n", "4",
            "--train_pairs", "8", "--sample_steps", "3", "--group_size", "4", "--tasks_per_step", "2", "--threads", "1",
            "--pick", "pickscore-tiny", "--lambda_pick", "1", "--lambda_task", "0", "--lambda_cons", "0",
            "--lambda_distill", "0", "--beta_d", "0", "--run_dir", str(d))
    assert r.returncode == 0, r.stderr
    recs = [json.loads(line) for line in open(d / "rl.jsonl")]
    steps, evals = [x for x in recs if "r_pick" in x], [x for x in recs if x.get("eval")]
    assert len(steps) == 2
    assert all(np.isfinite(x["r_pick"]) and x["adv_abs"] > 0.5 and x["grad_norm"] > 0 for x in steps)
    assert [x["step"] for x in evals] == [0, 1, 2] and all(np.isfinite(x["pick"]) for x in evals)
    assert "| pick |" in r.stdout and "r_pick" in r.stdout
    # with --lambda_pick 0 PickScore only measures (Fig. 4's quality panel): each evaluation records it, no rollout
    # is scored by it -- here beside Fig. 4 left's anchor-alone variant (train.anchor_only)
    r = run("train.py", "--toy", "--init", tiny_ckpt, "--steps", "1", "--eval_every", "1", "--eval_n", "4",
            "--train_pairs", "8", "--sample_steps", "3", "--group_size", "4", "--tasks_per_step", "2", "--threads", "1",
            "--pick", "pickscore-tiny", "--lambda_task", "0", "--lambda_cons", "0", "--lambda_distill", "0",
            "--run_dir", str(tmp_path / "measure"))
    assert r.returncode == 0, r.stderr
    recs = [json.loads(line) for line in open(tmp_path / "measure" / "rl.jsonl")]
    assert [x["step"] for x in recs if x.get("eval") and np.isfinite(x["pick"])] == [0, 1]
    assert not any("r_pick" in x for x in recs) and "| pick |" in r.stdout and "anchor alone" in r.stdout
    from PIL import Image
    assert Image.open(tmp_path / "measure" / "rl_curve.png").size[0] == 5 * 4 * 110    # a fifth panel: PickScore
    # bench.py --pick: the bench's videos scored against T, the weights from local directories; none there: an error
    import bench
    r = run("bench.py", "--checkpoint", tiny_ckpt, "--n", "3", "--steps", "2", "--threads", "1", "--pick", "pickscore",
            "--pick_path", str(tmp_path / "pick"), "--pick_processor_path", str(tmp_path / "proc"), "--json")
    assert r.returncode == 0, r.stderr
    _, videos, pairs = bench.evaluate(models.load_checkpoint(tiny_ckpt)[0].eval(), "task", 3, steps=2)
    full = reward.PickScore.from_pretrained(str(tmp_path / "pick"), str(tmp_path / "proc"))     # 4 frames a video
    assert json.loads(r.stdout.splitlines()[-1])["pick"] == pytest.approx(
        float(np.mean(full(videos, [p.task.text for p in pairs]))), abs=1e-4)
    assert "PickScore against T (mean over the videos): " in r.stdout
    r = run("bench.py", "--checkpoint", tiny_ckpt, "--n", "3", "--pick", "pickscore", "--pick_path", str(tmp_path))
    assert r.returncode == 2 and "PickScore model not found at" in r.stderr


@pytest.mark.parametrize("cls", [models.LTX2Video, models.HunyuanVideo15], ids=["ltx2", "hunyuan15"])
def test_a_real_model_evaluates_at_table_3s_evaluation_resolution(cls, tmp_path, monkeypatch):
    """models.resolution: inside it a real backend conditions, samples and decodes at another size (Table 3: LTX-2
    trains at 384 x 576 and is evaluated at 512 x 768), its latent grid scaled alike, and after it at its own size
    again; a size its VAE cannot take is a clear error. train.py --eval_height/--eval_width evaluates at it and
    trains at the model's size; bench.py --height/--width evaluates at it."""
    m = cls.tiny(world.VOCAB + ["[", "]:"])
    grid, size = m.latent_shape(), (m.height, m.width)
    pairs = world.make_pairs(2, seed=0, error_rate=0.0)
    f0, prompts = np.stack([p.frame0 for p in pairs]), [p.task.text for p in pairs]
    with models.resolution(m, 2 * m.height, 4 * m.width):
        assert m.latent_shape() == (*grid[:2], 2 * grid[2], 4 * grid[3])
        assert models.generate(m, f0, prompts, steps=1, seed=0).shape[2:4] == (2 * size[0], 4 * size[1])
    assert m.latent_shape() == grid and (m.height, m.width) == size
    own = models.generate(m, f0, prompts, steps=1, seed=0)
    assert own.shape[2:4] == size
    with pytest.raises(ValueError, match=r"not a multiple of \d+ x \d+, the pixels of one latent cell"):
        with models.resolution(m, m.height + 1, m.width):
            pass
    with pytest.raises(ValueError, match="for a real model"):
        with models.resolution(models.load_checkpoint(None)[0], 32, 32):
            pass
    if cls is models.HunyuanVideo15:        # the scripts: once is enough
        return
    train_data, bench_data = _toy_dataset(tmp_path / "train", 4, seed=5), _toy_dataset(tmp_path / "bench", 2, seed=6)
    evaluated, trained = [], []
    evaluate, rollouts = train.bench.evaluate, train._rollouts
    monkeypatch.setattr(train.bench, "evaluate", lambda model, *a, **k: evaluated.append(
        (model.height, model.width, k["pairs"][0].frame0.shape[:2])) or evaluate(model, *a, **k))
    monkeypatch.setattr(train, "_rollouts", lambda net, c, x_0, *a: trained.append(tuple(x_0.shape[-2:])) or
                        rollouts(net, c, x_0, *a))
    train.main(["--model", "ltx2-tiny", "--steps", "1", "--eval_n", "2", "--tasks_per_step", "2", "--group_size", "2",
                "--sample_steps", "2", "--dataset", train_data, "--eval_dataset", bench_data, "--eval_height", "32",
                "--eval_width", "64", "--run_dir", str(tmp_path / "run"), "--threads", "1"])
    assert len(evaluated) == 3 and set(evaluated) == {(32, 64, (32, 64))}    # base, Demonstrator, the Executor
    assert trained == [tuple(grid[-2:])]                                    # training at the model's own size
    err = run("train.py", "--model", "ltx2-tiny", "--eval_height", "65", "--eval_width", "96", "--run_dir",
              str(tmp_path / "never"))
    assert err.returncode == 2 and "is not a multiple of 2 x 2" in err.stderr and not (tmp_path / "never").exists()
    r = run("bench.py", "--model", "ltx2-tiny", "--dataset", bench_data, "--n", "2", "--steps", "2", "--height", "32",
            "--width", "64", "--png", str(tmp_path / "strip.png"))
    assert r.returncode == 0 and "task" in r.stdout, r.stderr
    frames, scale = own.shape[1], 6 * world.H // 32       # bench.save_strip: 2 videos of 32 x 64 a frame
    assert Image.open(tmp_path / "strip.png").size == (frames * 64 * scale, 2 * 32 * scale)
    r = run("bench.py", "--model", "ltx2-tiny", "--n", "2", "--height", "65", "--width", "96")
    assert r.returncode == 2 and "error: --height, --width: 65 x 96 is not a multiple" in r.stderr


def test_aesthetic_ranking_keeps_the_top_90_percent(tmp_path):
    assert list(world.aesthetic_top([0.3, 0.9, 0.1, 0.5, 0.7, 0.2, 0.8, 0.4, 0.6, 0.0])) == list(range(9))
    assert list(world.aesthetic_top([1.0])) == [0] and list(world.aesthetic_top([])) == []
    scorer = world.CLIPAesthetic.tiny()
    rng = np.random.default_rng(0)
    imgs = [rng.integers(0, 256, (40, 48, 3)).astype(np.uint8) for _ in range(3)]
    s = scorer(imgs)
    assert s.shape == (3,) and np.isfinite(s).all() and len(set(np.round(s, 6))) == 3

    class Everything:   # a VLM that finds every image suitable and answers with nothing parseable
        def yes_no(self, images, prompt):
            return [True] * len(images)

        def generate(self, images, prompt):
            return [""] * len(images)

    from PIL import Image
    paths = []
    for i in range(10):
        Image.fromarray(rng.integers(30, 220, (32, 32, 3)).astype(np.uint8)).save(tmp_path / f"{i}.png")
        paths.append(str(tmp_path / f"{i}.png"))
    counts = world.make_worldtasks(paths, Everything(), str(tmp_path / "wt.jsonl"), aesthetic=scorer)
    assert counts["low aesthetic score"] == 1 and counts["unsuitable"] == 0
    with pytest.raises(FileNotFoundError, match="aesthetic scorer weights not found"):
        world.CLIPAesthetic.from_pretrained(str(tmp_path / "no_clip"), str(tmp_path / "no_head.pt"))
    scorer.clip.save_pretrained(str(tmp_path / "clip"))        # from local paths: a CLIP directory and the head's file
    scorer.processor.save_pretrained(str(tmp_path / "clip"))
    torch.save(scorer.head.state_dict(), tmp_path / "head.pt")
    loaded = world.CLIPAesthetic.from_pretrained(str(tmp_path / "clip"), str(tmp_path / "head.pt"))
    assert np.array_equal(loaded(imgs), s)


def test_real_rollouts_a_thinned_gif_and_each_row_whole_as_an_mp4(tmp_path, monkeypatch, capsys):
    """train.write_rollout_gif: the toy's 16-px rows are enlarged 8x to 128 px; a real model's rows are at most
    128 px and not enlarged past that. The scale once came from the first frames, which are the toy bench's 16 px
    for a real model too: at LTX-2's size it wrote a 116 MB GIF of 1024-px rows (measured on a GPU). Here a tiny
    LTX-2 at 64 x 64: rows of 128 px (2x), not 512 (8x). Beside the GIF, each row whole (write_rollout_mp4s): an
    mp4 of every frame at the model's size, the Demonstrator left, the Executor right, indexed with their prompts;
    without PyAV a line says so and the GIF is still written."""
    import av
    m = models.LTX2Video.tiny(world.VOCAB + ["[", "]:"], height=64, width=64)
    m.fps = 12.0                     # not the default 24: the mp4s are at the model's rate
    train.BENCH = None
    args = train.Args(model="ltx2-tiny", sample_steps=1)
    train.write_rollout_gif(m, str(tmp_path / "g.gif"), args, n=2)
    gif = Image.open(tmp_path / "g.gif")
    assert gif.size == (2 * 128 + 2 * 2, 2 * 128) and gif.n_frames <= 24
    rows, pairs = [json.loads(line) for line in open(tmp_path / "g" / "videos.jsonl")], train.eval_pairs(args)[:2]
    assert rows == [{"video": f"00{i}.mp4", "task": p.task.text, "demonstrator": p.d_vlm, "executor": p.task.text}
                    for i, p in enumerate(pairs)]
    video = world.load_video(str(tmp_path / "g" / "001.mp4"))
    assert video.shape == (m.frames, 64, 2 * 64 + 2, 3) and (video[:, :, 64:66] > 200).all()
    with av.open(str(tmp_path / "g" / "001.mp4")) as c:
        assert c.streams.video[0].average_rate == 12
    made = {p.d_vlm: 40 for p in pairs} | {p.task.text: 160 for p in pairs}    # which video goes where: the
    monkeypatch.setattr(models, "generate", lambda net, frame0, prompts, *a, **k: np.stack(   # D's grey, T's light
        [np.full((m.frames, 64, 64, 3), made[c] + 20 * i, np.uint8) for i, c in enumerate(prompts)]))
    train.write_rollout_gif(m, str(tmp_path / "f.gif"), args, n=2)
    video = world.load_video(str(tmp_path / "f" / "001.mp4")).astype(int)
    assert np.abs(video[..., :64, :] - 60).max() <= 2 and np.abs(video[..., 66:, :] - 180).max() <= 2
    spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "av" else spec(name, *a))
    train.write_rollout_gif(m, str(tmp_path / "h.gif"), args, n=2)
    assert (tmp_path / "h.gif").exists() and not (tmp_path / "h").exists()
    assert "h/*.mp4 not written: PyAV is not installed" in capsys.readouterr().out


@pytest.mark.parametrize("cls", [models.LTX2Video, models.HunyuanVideo15], ids=["ltx2", "hunyuan15"])
def test_a_real_model_encodes_a_video_into_the_state_it_decodes(cls):
    """encode_video, the +SFT baseline's data: a video becomes the state x_1 that sampling ends in (latent_shape),
    which decode turns back into the VAE's own round trip of the video (encode, decode, frame 0 the given one). So
    the latents are normalised as decode reads them, and the latent frames kept are the ones the model generates.
    Frames of another size are resized to the model's; another frame count is an error."""
    m = cls.tiny(world.VOCAB + ["[", "]:"], seed=0)
    if cls is models.LTX2Video:      # the tiny VAE's statistics are 0 and 1: made other, so normalising shows
        g = torch.Generator().manual_seed(0)
        m.vae.latents_mean.copy_(torch.randn(m.vae.latents_mean.shape, generator=g))
        m.vae.latents_std.copy_(torch.rand(m.vae.latents_std.shape, generator=g) + 0.5)
    video = np.random.default_rng(0).integers(0, 256, (2, m.frames, 24, 40, 3), dtype=np.uint8)
    x_1 = m.encode_video(video)
    assert x_1.shape == (2, *m.latent_shape())
    img = models._video_batch(video, m.frames, m.height, m.width)
    assert img.shape == (2, 3, m.frames, m.height, m.width)
    with torch.no_grad():
        raw = torch.cat([m.vae.decode(m.vae.encode(img[i:i + 1]).latent_dist.mode(), return_dict=False)[0]
                         for i in range(2)]).float()
    want = models._with_first_frame(raw, video[:, 0])
    assert np.abs(m.decode(x_1, video[:, 0]).astype(int) - want).max() <= 1
    with pytest.raises(ValueError, match=f"this model takes \\(B, {m.frames}, H, W, 3\\)"):
        m.encode_video(video[:, :-1])


def test_the_sft_baseline_on_a_real_model_trains_its_lora_on_a_file_of_labelled_videos(tmp_path, monkeypatch):
    """Table 1's +SFT row on a real model (train.py --stage distill --variant sft --sft_dataset FILE): the
    flow-matching loss (App. A.9, unweighted) on the file's videos, encoded by the model (encode_video) and
    conditioned on their first frame and task; every row checked before training, a bad one a clear error naming
    its line; the run trains the LoRA, --micro_batch videos a pass, and saves it for bench.py --lora."""
    m = models.LTX2Video.tiny(world.VOCAB + ["[", "]:"], seed=0)
    rng = np.random.default_rng(0)
    np.save(tmp_path / "v0.npy", rng.integers(0, 256, (m.frames, 24, 40, 3), dtype=np.uint8))
    np.save(tmp_path / "v1.npy", rng.integers(0, 256, (m.frames, m.height, m.width, 3), dtype=np.uint8))
    frames = [Image.fromarray(rng.integers(0, 256, (16, 16, 3), dtype=np.uint8)) for _ in range(m.frames)]
    frames[0].save(tmp_path / "g.gif", save_all=True, append_images=frames[1:], loop=0)
    tasks = ["[red square]: move right", "[blue circle]: go to the left edge", "[first-person view]: look up"]
    path = tmp_path / "sft.jsonl"
    path.write_text("".join(json.dumps({"video": v, "task": t}) + "\n" for v, t in zip(("v0.npy", "v1.npy", "g.gif"),
                                                                                      tasks)))
    rows = train.sft_rows(str(path), m, 3)
    assert [r["video"] for r in rows] == [str(tmp_path / f) for f in ("v0.npy", "v1.npy", "g.gif")]
    videos = np.stack([world.load_video(r["video"], (m.width, m.height)) for r in rows])
    assert videos.shape == (3, m.frames, m.height, m.width, 3)
    assert np.array_equal(videos[1], np.load(tmp_path / "v1.npy"))                       # at the model's size: as is
    assert np.array_equal(videos[2, 1], np.asarray(frames[1].resize((m.width, m.height), Image.BILINEAR)))
    torch.manual_seed(3)
    got = train.video_loss(m, videos, tasks, train.Args())
    torch.manual_seed(3)
    x_1, c = m.encode_video(videos), m.condition(videos[:, 0], tasks)
    x_0 = torch.randn_like(x_1)
    t = torch.rand(3)
    x_t = (1 - t).view(-1, 1, 1, 1, 1) * x_0 + t.view(-1, 1, 1, 1, 1) * x_1
    with torch.no_grad():
        assert torch.allclose(got, (m(x_t, t, c) - (x_1 - x_0)).pow(2).mean())
    # bad rows, each named by its line
    np.save(tmp_path / "short.npy", np.zeros((m.frames - 1, 8, 8, 3), np.uint8))
    np.save(tmp_path / "floats.npy", np.zeros((m.frames, 8, 8, 3), np.float32))
    (tmp_path / "clip.mp4").write_bytes(b"\x00\x00\x00\x18ftypmp42")
    good = json.dumps({"video": "v1.npy", "task": tasks[0]})
    for bad, msg in (("{", "line 2: Expecting property name"), (json.dumps({"video": "v1.npy"}), 'a row is {"video"'),
                     (json.dumps({"video": "none.npy", "task": "x"}), "line 2: [Errno 2] No such file"),
                     (json.dumps({"video": "short.npy", "task": "x"}), f"has {m.frames - 1} frames; the model makes"),
                     (json.dumps({"video": "floats.npy", "task": "x"}), "a .npy video is uint8 (F, H, W, 3), not float32"),
                     (json.dumps({"video": "clip.mp4", "task": "x"}), "line 2: [Errno 1094995529] Invalid data found")):
        (tmp_path / "bad.jsonl").write_text(good + "\n" + bad + "\n")
        with pytest.raises(ValueError) as e:
            train.sft_rows(str(tmp_path / "bad.jsonl"), m, 1)
        assert msg in str(e.value) and str(e.value).startswith(str(tmp_path / "bad.jsonl")), (bad, str(e.value))
    with pytest.raises(ValueError, match="--sft_dataset '.*' is a directory, not a JSONL file"):
        train.sft_rows(str(tmp_path), m, 1)                # one line, not an IsADirectoryError's traceback
    (tmp_path / "bad.jsonl").write_text(json.dumps({"video": "v1.npy", "task": "[red square]: " + "go " * 300}))
    with pytest.raises(ValueError, match="line 1: prompt .* tokens; LTX-2's text path takes at most"):
        train.sft_rows(str(tmp_path / "bad.jsonl"), m, 1)
    with pytest.raises(ValueError, match="has 3 videos, fewer than --batch 4"):
        train.sft_rows(str(path), m, 4)
    r = run("train.py", "--stage", "distill", "--variant", "sft", "--model", "ltx2-tiny", "--sft_dataset",
            str(tmp_path / "none.jsonl"), "--run_dir", str(tmp_path / "none"))
    assert r.returncode == 2 and "none.jsonl' does not exist" in r.stderr and not (tmp_path / "none").exists()
    r = run("train.py", "--stage", "distill", "--variant", "sft", "--model", "ltx2-tiny", "--sft_dataset", str(path),
            "--eval_height", "33", "--eval_width", "32", "--run_dir", str(tmp_path / "none"))   # a size the VAE cannot take
    assert r.returncode == 2 and "33" in r.stderr and not (tmp_path / "none").exists(), r.stderr
    # a step: each video with its own task, --micro_batch videos a pass
    seen = []

    def recording(model, videos, captions, args):
        seen.append((videos.copy(), list(captions)))
        return sum(p.sum() for p in models.lora_parameters(model)) * 0.0
    monkeypatch.setattr(train, "video_loss", recording)
    monkeypatch.setattr(train, "evaluate_executor", lambda *a, **k: {k: 0.0 for k in train.EVAL_KEYS})
    monkeypatch.setattr(train, "write_rollout_gif", lambda *a, **k: None)
    train.main(["--stage", "distill", "--variant", "sft", "--model", "ltx2-tiny", "--sft_dataset", str(path),
                "--steps", "1", "--batch", "3", "--micro_batch", "2", "--threads", "1", "--run_dir", str(tmp_path / "r")])
    assert [len(c) for _, c in seen] == [2, 1]
    for vs, cs in seen:
        for v, c in zip(vs, cs):
            assert c == tasks[next(i for i in range(3) if np.array_equal(v, videos[i]))]
    monkeypatch.undo()
    # the run
    d, held = tmp_path / "run", _toy_dataset(tmp_path / "held", 2, seed=6)     # evaluated on a WorldTasks file
    r = run("train.py", "--stage", "distill", "--variant", "sft", "--model", "ltx2-tiny", "--sft_dataset", str(path),
            "--steps", "2", "--batch", "3", "--micro_batch", "2", "--eval_every", "1", "--eval_n", "2",
            "--log_every", "1", "--sample_steps", "2", "--threads", "1", "--judge", "qwen-vl-tiny", "--eval_dataset",
            held, "--grad_checkpoint", "--offload_text", "--run_dir", str(d))
    assert r.returncode == 0, r.stderr
    assert "Demonstrator (base given the bench file's D)" in r.stdout
    assert json.load(open(d / "distill_summary.json"))["bench"] == held
    recs = [json.loads(line) for line in open(d / "distill.jsonl")]
    assert [x["step"] for x in recs if x.get("eval")] == [0, 1, 2]
    steps = [x for x in recs if not x.get("eval")]
    assert len(steps) == 2 and all(np.isfinite(x["loss"]) and x["grad_norm"] > 0 for x in steps)
    saved = torch.load(d / "executor_sft.pt", weights_only=True)
    assert saved["meta"]["variant"] == "sft" and any(v.abs().sum() > 0 for k, v in saved["lora"].items()
                                                     if "lora_B" in k)                   # B starts at 0: trained
    assert "3 labelled videos from" in r.stdout and (d / "rollouts_sft.gif").exists()
    assert (d / "rollouts_sft" / "000.mp4").exists()                  # the GIF's rows whole
    r = run("bench.py", "--model", "ltx2-tiny", "--lora", str(d / "executor_sft.pt"), "--n", "2", "--steps", "2")
    assert r.returncode == 0 and "2 steps of --model ltx2-tiny" in r.stdout, r.stderr


def _write_video(path, frames, codec="libx264"):
    """uint8 (F, H, W, 3) -> a video file through PyAV: H.264 lossless in 4:4:4 (RGB comes back within a level or
    so), or VP9 in 4:2:0 for a .webm, whose header does not hold its frame count."""
    import av
    with av.open(str(path), "w") as c:
        s = c.add_stream(codec, rate=8, options={"crf": "0"} if codec == "libx264" else {})
        s.width, s.height, s.pix_fmt = frames.shape[2], frames.shape[1], "yuv444p" if codec == "libx264" else "yuv420p"
        for f in frames:
            c.mux(s.encode(av.VideoFrame.from_ndarray(f, format="rgb24")))
        c.mux(s.encode())


def test_an_mp4_or_webm_video_is_read_through_pyav_and_without_it_is_a_clear_error(tmp_path, monkeypatch, capsys):
    """world.load_video and video_length read video containers (mp4, webm, ...) through PyAV, an optional package of
    requirements-real.txt: the frames that were written, their count from the header or, where the header has none
    (webm), by decoding. A file PyAV cannot read is a ValueError, counted as unreadable by label_videos. Without PyAV,
    --sft_dataset names the row and the install, and world.py --label_videos says so before loading the VLM."""
    y, x = np.mgrid[:32, :48]
    v = np.stack([np.stack([4 * x + 8 * i, 6 * y, np.full_like(x, 40 * i)], -1) for i in range(5)]).astype(np.uint8)
    v[2, 10:20, 12:24] = (250, 20, 20)
    _write_video(tmp_path / "v.mp4", v)
    _write_video(tmp_path / "v.webm", v, "libvpx-vp9")
    import av
    with av.open(str(tmp_path / "v.webm")) as c:
        assert c.streams.video[0].frames == 0                  # so video_length counts by decoding
    assert world.video_length(str(tmp_path / "v.mp4")) == world.video_length(str(tmp_path / "v.webm")) == 5
    got = world.load_video(str(tmp_path / "v.mp4"))
    assert got.dtype == np.uint8 and got.shape == v.shape and np.abs(got.astype(int) - v).max() <= 2
    webm = world.load_video(str(tmp_path / "v.webm"), size=(24, 16))
    assert webm.shape == (5, 16, 24, 3) and np.abs(webm.astype(int) - v[:, 1::2, 1::2]).mean() < 8
    with monkeypatch.context() as mp:             # a header that miscounts: an error, not a short video mid-run
        mp.setattr(world, "video_length", lambda path: 6)
        with pytest.raises(ValueError, match="v.mp4: 5 frames decoded where its header counts 6"):
            world.load_video(str(tmp_path / "v.mp4"))
    (tmp_path / "bad.mp4").write_bytes(b"\x00\x00\x00\x18ftypmp42")
    with pytest.raises(ValueError, match="Invalid data"):
        world.video_length(str(tmp_path / "bad.mp4"))
    with av.open(str(tmp_path / "sound.mp4"), "w") as c:                  # sound alone: no frame to count
        s = c.add_stream("aac", rate=8000)
        f = av.AudioFrame.from_ndarray(np.zeros((1, 1024), np.float32), format="fltp", layout="mono")
        f.sample_rate = 8000
        c.mux(s.encode(f))
        c.mux(s.encode())
    with pytest.raises(ValueError, match="sound.mp4: no video stream"):
        world.video_length(str(tmp_path / "sound.mp4"))
    m = models.LTX2Video.tiny(world.VOCAB + ["[", "]:"], seed=0)                      # 5 frames a video
    (tmp_path / "sft.jsonl").write_text(json.dumps({"video": "v.mp4", "task": "[red square]: go to the left edge"}))
    assert [r["video"] for r in train.sft_rows(str(tmp_path / "sft.jsonl"), m, 1)] == [str(tmp_path / "v.mp4")]
    import importlib.util
    find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "av" else find_spec(name, *a))
    with pytest.raises(ValueError, match="sft.jsonl line 1: the real-model path needs av: pip install"):
        train.sft_rows(str(tmp_path / "sft.jsonl"), m, 1)
    with pytest.raises(SystemExit) as e:
        world.main(["--label_videos", str(tmp_path / "v.mp4"), "--judge", "qwen-vl-tiny", "--out",
                    str(tmp_path / "x.jsonl")])
    assert e.value.code == 2 and "needs av: pip install" in capsys.readouterr().err
    assert not (tmp_path / "x.jsonl").exists()


def test_a_real_models_bench_videos_are_written_as_mp4s_at_its_frame_rate(tmp_path):
    """bench.save_videos with a real model's frame rate (bench.py --videos): each video an mp4 through
    world.write_video, H.264 at crf 18, which reads back as the frames written, to within what the codec loses; an
    odd height or width loses its last row or column (4:2:0 needs them even)."""
    import av
    import bench
    y, x = np.mgrid[:33, :31]
    v = np.stack([np.stack([6 * x + 10 * i, 5 * y, np.full_like(x, 20 * i)], -1) for i in range(9)]).astype(np.uint8)
    videos = np.stack([v, v[::-1]])
    pairs = [SimpleNamespace(task=SimpleNamespace(text=t)) for t in ("[a]: go", "[b]: stop")]
    verdicts = {"task": [True, None], "agent": [False, True], "consistency": [True, True]}
    index = bench.save_videos(str(tmp_path / "out"), videos, [
        {"task": p.task.text, "prompt": d, "verdicts": {k: verdicts[k][i] for k in bench.KEYS}}
        for i, (p, d) in enumerate(zip(pairs, ["D a", "D b"]))], fps=24.0)
    rows = [json.loads(line) for line in open(index)]
    assert rows[1] == {"video": "001.mp4", "task": "[b]: stop", "prompt": "D b",
                       "verdicts": {"task": None, "agent": True, "consistency": True}}
    for i, r in enumerate(rows):
        got = world.load_video(str(tmp_path / "out" / r["video"]))
        assert got.shape == (9, 32, 30, 3) and np.abs(got.astype(int) - videos[i, :, :32, :30]).mean() < 3
        with av.open(str(tmp_path / "out" / r["video"])) as c:
            assert c.streams.video[0].average_rate == 24 and c.streams.video[0].codec_context.name == "h264"


def test_label_videos_writes_the_sft_file_from_the_vlms_answers(tmp_path):
    """world.label_videos, Sec. 4.4's +SFT data: each unannotated video given to the VLM with VIDEO_TASK_PROMPT, the
    first "[agent]: instruction" line of its answer kept as the video's task, an answer with none or a file that is
    no video dropped and counted; the file it writes is what train.py --sft_dataset reads. The tiny Qwen3-VL's
    generate takes a video (its frames, as the judges read them) as well as a still image."""
    rng = np.random.default_rng(0)
    for i in range(3):
        np.save(tmp_path / f"v{i}.npy", rng.integers(0, 256, (5, 32, 32, 3), dtype=np.uint8))
    (tmp_path / "clip.mp4").write_bytes(b"\x00\x00\x00\x18ftypmp42")

    class VLM:
        asked = []

        def generate(self, videos, prompt):
            self.asked.append((np.asarray(videos[0]).shape, prompt))
            return [{0: "Sure.\nTask: [Red car]:  park   beside the curb.", 1: "I cannot tell.",
                     2: "[First-person view]: look up"}[len(self.asked) - 1]]
    out = tmp_path / "sub" / "sft.jsonl"
    out.parent.mkdir()
    counts = world.label_videos([str(tmp_path / f) for f in ("v0.npy", "v1.npy", "clip.mp4", "v2.npy")], VLM(),
                                str(out))
    assert counts == {"videos": 4, "labelled": 2, "unreadable": 1, "malformed": 1}
    assert VLM.asked[0] == ((5, 32, 32, 3), world.VIDEO_TASK_PROMPT) and len(VLM.asked) == 3
    rows = [json.loads(line) for line in open(out)]
    assert rows == [{"video": "../v0.npy", "task": "[Red car]: park beside the curb."},
                    {"video": "../v2.npy", "task": "[First-person view]: look up"}]
    m = models.LTX2Video.tiny(world.VOCAB + ["[", "]:"], seed=0)                      # 5 frames a video
    assert [r["video"] for r in train.sft_rows(str(out), m, 2)] == [str(tmp_path / "sub" / "../v0.npy"),
                                                                   str(tmp_path / "sub" / "../v2.npy")]
    judge = reward.VLMJudge.tiny([])
    answers = judge.generate([np.load(tmp_path / "v0.npy"), np.load(tmp_path / "v0.npy")[0]], "Which task?",
                             max_new_tokens=3)
    assert len(answers) == 2 and all(isinstance(a, str) for a in answers)
    # from the shell: python world.py --label_videos VIDEO ... --judge ... --out FILE (--worldtasks IMAGE ... alike)
    r = run("world.py", "--label_videos", str(tmp_path / "v0.npy"), str(tmp_path / "clip.mp4"), "--judge",
            "qwen-vl-tiny", "--out", str(tmp_path / "new" / "sft.jsonl"))
    assert r.returncode == 0 and "videos 2, labelled" in r.stdout and "unreadable 1" in r.stdout, r.stderr
    assert (tmp_path / "new" / "sft.jsonl").exists()       # random weights: most likely no task in the answer
    Image.fromarray(np.load(tmp_path / "v0.npy")[0]).save(tmp_path / "f.png")
    r = run("world.py", "--worldtasks", str(tmp_path / "f.png"), "--judge", "qwen-vl-tiny", "--out",
            str(tmp_path / "wt.jsonl"))
    assert r.returncode == 0 and "images 1, kept_images" in r.stdout and (tmp_path / "wt.jsonl").exists(), r.stderr
    for argv, msg in ((["--label_videos", "v.npy"], "--label_videos writes the JSONL file --out: give one"),
                      (["--label_videos", "v.npy", "--out", "x.png"], "--out 'x.png' must end in .jsonl"),
                      (["--label_videos", "v.npy", "--out", "x.jsonl"], "--judge qwen-vl needs --judge_path"),
                      (["--label_videos", "v.npy", "--worldtasks", "i.png", "--out", "x.jsonl"], "not with each other"),
                      (["--label_videos", "v.npy", "--out", "x.jsonl", "--judge_path", str(tmp_path)],
                       "is not a transformers model directory: it has no config.json"),
                      (["--judge", "qwen-vl-tiny"], "--judge and --judge_path are read with --worldtasks or")):
        r = run("world.py", *argv)
        assert r.returncode == 2 and msg in r.stderr, (argv, r.stderr)
