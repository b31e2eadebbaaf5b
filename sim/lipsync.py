"""Audio-driven lip sync: LPC cepstrum of each audio frame -> a small neural net -> the 13 mouth parameters.

Yotsukura et al., HYPERMASK, §4: speech at 16 kHz is cut into 32 ms frames; each frame's 20th-order LPC
cepstrum feeds a three-layer feed-forward net (20 inputs, 20 hidden units, 13 outputs) whose outputs are
the mouth parameters of sim.mouth. The net learns the five vowels and the closed mouth (from room noise),
so a frame of speech lands near the vowel its spectral envelope resembles. Weights depend strongly on the
speaker, so §4.1 keeps a bank of weight sets, one per training voice, and adapts to a new speaker by
asking each set to reproduce that speaker's five vowels and keeping the set that does it best.

    samples = load_audio("line.wav")                       # float64 mono at 16 kHz
    params = mouth_track(samples, fps=24)                   # (T, 13) mm, with the shipped general set
    choice = choose_weights(load_bank(), {"a": a, "i": i, "u": u, "e": e, "o": o})
    params = mouth_track(samples, fps=24, weights=choice.weights)

The shipped bank (data/lipsync_bank.npz) and the demo line (data/demo_line.wav) are made by this module's
command, with the espeak-ng synthesiser standing in for the paper's recorded speakers:

    python -m sim.lipsync train -o sim/data/lipsync_bank.npz
    python -m sim.lipsync demo-line -o sim/data/demo_line.wav

Training holds each vowel with espeak-ng's Japanese voice (`espeak-ng -v ja+VARIANT -p PITCH -s 90 -w
out.wav "[[a:]]"`: about 0.6 s of vowel, at three pitches per voice), pads it with silence, adds quiet white
noise as the room, also hears it through random spectral tilts, and fits each net with L-BFGS (about three
minutes on two cores). The file lists the voices it was trained on, so tests can pick voices it never
heard. The demo line is `espeak-ng -v en+m3 -s 175` speaking DEMO_LINE, resampled to 16 kHz, 16-bit mono.
"""

import argparse
import math
import os
import shutil
import subprocess
import sys
import tempfile
import warnings
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import NamedTuple

import numpy as np
from scipy.io import wavfile
from scipy.ndimage import gaussian_filter1d

from .errors import InputError
from .mouth import NUM_MOUTH_PARAMETERS, VOWEL_SHAPES, VOWELS, nearest_vowel

SAMPLE_RATE = 16000  # Hz, Yotsukura et al. §4
FRAME_LENGTH = 512  # samples: 32 ms at 16 kHz, §4
FRAME_SECONDS = FRAME_LENGTH / SAMPLE_RATE
LPC_ORDER = 20  # also the number of cepstral coefficients, §4
HIDDEN_UNITS = 20  # §4, chosen empirically by the authors
PRE_EMPHASIS = 0.97
# Power of a white floor (-100 dBFS) added to every frame's autocorrelation, so that digital silence still
# has a defined, deterministic LPC fit (all-zero predictor, all-zero cepstrum).
NOISE_FLOOR_RMS = 1e-5
SPOKEN_VOWELS = VOWELS[:5]
CLOSED = VOWELS.index("closed")

DATA_DIR = Path(__file__).resolve().parent / "data"
BANK_PATH = DATA_DIR / "lipsync_bank.npz"
DEMO_LINE_PATH = DATA_DIR / "demo_line.wav"

# espeak-ng variants of the Japanese voice the shipped bank is trained on, one weight set each. Variants
# m7, m8, f3 and the Klatt-synthesiser voices are kept out, for testing on speakers the bank never heard.
TRAINING_VOICES = ("ja+m1", "ja+m2", "ja+m3", "ja+m4", "ja+m5", "ja+m6",
                   "ja+f1", "ja+f2", "ja+f4", "ja+f5", "ja+Andy", "ja+linda")
TRAINING_PITCHES = (35, 50, 65)  # espeak-ng -p, 0..99
TRAINING_SPEED = 90  # espeak-ng -s, words per minute: holds a vowel ~0.6 s
DEMO_LINE = "Hello. I am made of warp kernels, and I can talk."
DEMO_VOICE = "en+m3"


# ---------------------------------------------------------------------------------------------- audio

def load_audio(path):
    """A WAV file as float64 mono samples in [-1, 1] at 16 kHz (channels averaged, resampled)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "audio", "file not found" if not path.exists() else "not a file")
    try:
        with warnings.catch_warnings(record=True) as caught:  # chunks it skips (metadata) are no concern
            warnings.simplefilter("always", wavfile.WavFileWarning)
            rate, data = wavfile.read(path)
    except (ValueError, OSError) as err:
        raise InputError(path, "audio", f"not a readable WAV file ({err})") from None
    for warning in caught:
        if "EOF" in str(warning.message):  # a cut-off download or copy: the line would end early, unsaid
            raise InputError(path, "audio", f"truncated: {warning.message}")
    samples = _to_float(np.asarray(data))
    if samples.ndim == 2:
        samples = samples.mean(axis=1)
    if samples.size == 0:
        raise InputError(path, "audio", "the file holds no samples")
    if not np.all(np.isfinite(samples)):  # a float WAV can hold them; the mouth would follow them to NaN
        raise InputError(path, "audio", "samples that are NaN or infinite")
    return resample(samples, rate)


def _to_float(data):
    if data.dtype == np.uint8:
        return (data.astype(np.float64) - 128.0) / 128.0
    if np.issubdtype(data.dtype, np.integer):
        return data.astype(np.float64) / -float(np.iinfo(data.dtype).min)
    return data.astype(np.float64)


def resample(samples, rate):
    """Samples at `rate` Hz -> float64 at 16 kHz (polyphase, anti-aliased)."""
    samples = np.asarray(samples, np.float64)
    rate = int(rate)
    if rate == SAMPLE_RATE:
        return samples.copy()
    from scipy.signal import resample_poly  # imported here: scipy.signal alone takes ~0.9 s to import

    g = math.gcd(rate, SAMPLE_RATE)
    return resample_poly(samples, SAMPLE_RATE // g, rate // g)


def write_wav(path, samples):
    """16 kHz float samples -> 16-bit mono WAV."""
    pcm = np.clip(np.round(np.asarray(samples, np.float64) * 32767.0), -32768, 32767).astype(np.int16)
    wavfile.write(path, SAMPLE_RATE, pcm)


# ------------------------------------------------------------------------------------------- analysis

def _frames_at(samples, times):
    """(N, 512) raw frames centred at `times` [s], zero outside the signal."""
    samples = np.asarray(samples, np.float64)
    times = np.atleast_1d(np.asarray(times, np.float64))
    half = FRAME_LENGTH // 2
    padded = np.concatenate([np.zeros(FRAME_LENGTH), samples, np.zeros(FRAME_LENGTH)])
    start = np.round(times * SAMPLE_RATE).astype(np.int64) - half + FRAME_LENGTH
    start = np.clip(start, 0, padded.size - FRAME_LENGTH)
    return padded[start[:, None] + np.arange(FRAME_LENGTH)]


def frame_times(samples, hop=FRAME_SECONDS):
    """Centres [s] of frames every `hop` seconds over the whole signal (the paper's 32 ms period by default)."""
    duration = len(samples) / SAMPLE_RATE
    return np.arange(0.0, duration, hop)


def frame_energy_db(samples, times):
    """RMS level of the 32 ms frame centred at each time, dB re full scale (a full-scale sine is -3 dB)."""
    samples = np.asarray(samples, np.float64)
    power = np.concatenate([[0.0], np.cumsum(samples * samples)])
    centre = np.round(np.atleast_1d(np.asarray(times, np.float64)) * SAMPLE_RATE).astype(np.int64)
    start = np.clip(centre - FRAME_LENGTH // 2, 0, samples.size)
    stop = np.clip(centre + FRAME_LENGTH // 2, 0, samples.size)
    mean_square = np.maximum(power[stop] - power[start], 0.0) / FRAME_LENGTH
    return 10.0 * np.log10(np.maximum(mean_square, 1e-20))


def autocorrelation(frames, order):
    """Biased autocorrelation r[0..order] of each row, via the FFT."""
    n = frames.shape[-1]
    nfft = 1 << int(np.ceil(np.log2(2 * n)))
    spec = np.fft.rfft(frames, nfft)
    return np.fft.irfft(spec.real ** 2 + spec.imag ** 2, nfft)[..., :order + 1]


def levinson_durbin(r, order):
    """Predictor coefficients a (x[n] ~ sum_k a_k x[n-k]) and residual power from autocorrelations (N, >order).

    Runs the recursion for all frames at once; the loop is over the model order only."""
    r = np.atleast_2d(np.asarray(r, np.float64))
    a = np.zeros((r.shape[0], order))
    err = r[:, 0].copy()
    for i in range(order):
        k = (r[:, i + 1] - np.einsum("nk,nk->n", a[:, :i], r[:, i:0:-1])) / err
        prev = a[:, :i].copy()
        a[:, i] = k
        a[:, :i] = prev - k[:, None] * prev[:, ::-1]
        err = err * (1.0 - k * k)
    return a, err


def lpc(frames, order=LPC_ORDER):
    """LPC of each (already windowed) frame: predictor coefficients (N, order) and residual power (N,)."""
    frames = np.atleast_2d(np.asarray(frames, np.float64))
    r = autocorrelation(frames, order)
    floor = NOISE_FLOOR_RMS ** 2 * frames.shape[1]
    r[:, 0] = r[:, 0] * (1.0 + 1e-9) + floor
    return levinson_durbin(r, order)


def lpc_to_cepstrum(a, count=LPC_ORDER):
    """Cepstrum c_1..c_count of the all-pole model 1 / (1 - sum_k a_k z^-k), by the usual recursion.

    c_n = a_n + sum_{k=1}^{n-1} (k/n) c_k a_{n-k}, with a_n = 0 beyond the model order; c_0 (the gain) is
    left out, so the cepstrum describes the spectral envelope's shape, not its level."""
    a = np.atleast_2d(np.asarray(a, np.float64))
    p = a.shape[1]
    c = np.zeros((a.shape[0], count))
    for n in range(1, count + 1):
        acc = a[:, n - 1].copy() if n <= p else np.zeros(a.shape[0])
        for k in range(max(1, n - p), n):
            acc += (k / n) * c[:, k - 1] * a[:, n - k - 1]
        c[:, n - 1] = acc
    return c


def cepstra(samples, times):
    """20 LPC cepstral coefficients of the 32 ms frame centred at each time [s]: (N, 20)."""
    samples = np.asarray(samples, np.float64)
    emphasised = np.concatenate([samples[:1], samples[1:] - PRE_EMPHASIS * samples[:-1]])
    frames = _frames_at(emphasised, times) * np.hamming(FRAME_LENGTH)
    a, _ = lpc(frames, LPC_ORDER)
    return lpc_to_cepstrum(a, LPC_ORDER)


# ------------------------------------------------------------------------------------------------ net

_OUTPUT_SCALE = 10.0  # mm: the net is trained on targets / 10 mm, folded back into w2, b2 afterwards


@dataclass(frozen=True)
class MouthNet:
    """One weight set: cepstrum (20) -> tanh hidden layer (20) -> mouth parameters (13) [mm]."""

    name: str
    mean: np.ndarray  # (20,) input normalisation: z = (c - mean) / scale
    scale: np.ndarray  # (20,)
    w1: np.ndarray  # (20, 20)
    b1: np.ndarray  # (20,)
    w2: np.ndarray  # (20, 13), mm per unit of hidden activation
    b2: np.ndarray  # (13,) mm

    def __call__(self, cepstra):
        z = (np.asarray(cepstra, np.float64) - self.mean) / self.scale
        return np.tanh(z @ self.w1 + self.b1) @ self.w2 + self.b2


def _unpack(theta, n_in, n_hidden, n_out):
    shapes = [(n_in, n_hidden), (n_hidden,), (n_hidden, n_out), (n_out,)]
    out, at = [], 0
    for s in shapes:
        size = int(np.prod(s))
        out.append(theta[at:at + size].reshape(s))
        at += size
    return out


def train_net(cepstra, targets, name, weights=None, seed=0, weight_decay=1e-3, max_iter=800):
    """Fit a MouthNet to frames (N, 20) -> targets (N, 13) [mm] by weighted least squares with L-BFGS.

    `weights` (N,) balance the classes (all ones by default); weight decay keeps a per-voice set, trained on
    a few hundred frames, from memorising them. Deterministic for a given seed."""
    x = np.asarray(cepstra, np.float64)
    y = np.asarray(targets, np.float64) / _OUTPUT_SCALE
    w = np.ones(len(x)) if weights is None else np.asarray(weights, np.float64)
    w = w / w.sum()
    mean, scale = x.mean(axis=0), x.std(axis=0) + 1e-8
    z = (x - mean) / scale
    n_in, n_out = x.shape[1], y.shape[1]
    rng = np.random.default_rng(seed)
    theta0 = np.concatenate([
        rng.normal(0.0, 1.0 / np.sqrt(n_in), n_in * HIDDEN_UNITS), np.zeros(HIDDEN_UNITS),
        rng.normal(0.0, 1.0 / np.sqrt(HIDDEN_UNITS), HIDDEN_UNITS * n_out), np.zeros(n_out)])

    def loss(theta):
        w1, b1, w2, b2 = _unpack(theta, n_in, HIDDEN_UNITS, n_out)
        h = np.tanh(z @ w1 + b1)
        res = h @ w2 + b2 - y
        wres = w[:, None] * res
        value = 0.5 * np.sum(wres * res) + 0.5 * weight_decay * (np.sum(w1 * w1) + np.sum(w2 * w2))
        g_w2 = h.T @ wres + weight_decay * w2
        g_b2 = wres.sum(axis=0)
        dh = (wres @ w2.T) * (1.0 - h * h)
        g_w1 = z.T @ dh + weight_decay * w1
        g_b1 = dh.sum(axis=0)
        return value, np.concatenate([g_w1.ravel(), g_b1, g_w2.ravel(), g_b2])

    from scipy.optimize import minimize  # training only: kept out of every run's start-up

    result = minimize(loss, theta0, jac=True, method="L-BFGS-B",
                      options={"maxiter": max_iter, "maxfun": 2 * max_iter, "gtol": 1e-9, "ftol": 1e-14})
    w1, b1, w2, b2 = _unpack(result.x, n_in, HIDDEN_UNITS, n_out)
    return MouthNet(name, mean, scale, w1.copy(), b1.copy(), w2 * _OUTPUT_SCALE, b2 * _OUTPUT_SCALE)


@dataclass(frozen=True)
class LipSyncBank:
    """Weight sets, one per training voice (§4.1's database) plus 'general', trained on all the voices."""

    sets: tuple  # MouthNet, ...
    voices: tuple  # the espeak-ng voices the sets were trained on

    @property
    def names(self):
        return tuple(s.name for s in self.sets)

    @property
    def general(self):
        return self.sets[self.names.index("general")]

    def save(self, path):
        """Write the bank as a small .npz (float32 weights, no pickles)."""
        stack = lambda field: np.stack([getattr(s, field) for s in self.sets]).astype(np.float32)  # noqa: E731
        np.savez_compressed(
            path, names=np.array(self.names), voices=np.array(self.voices),
            mean=stack("mean"), scale=stack("scale"), w1=stack("w1"), b1=stack("b1"), w2=stack("w2"),
            b2=stack("b2"), sample_rate=SAMPLE_RATE, frame_length=FRAME_LENGTH, lpc_order=LPC_ORDER)


def load_bank(path=None):
    """Read a bank written by LipSyncBank.save; the shipped one when path is None."""
    path = Path(BANK_PATH if path is None else path)
    if path == BANK_PATH:
        return _shipped_bank()
    return _read_bank(path)


@lru_cache(maxsize=1)
def _shipped_bank():
    return _read_bank(BANK_PATH)


def _read_bank(path):
    if not path.is_file():
        raise InputError(path, "lipsync bank", "file not found")
    try:
        with np.load(path, allow_pickle=False) as f:
            data = {k: f[k] for k in f.files}
    except (ValueError, OSError) as err:
        raise InputError(path, "lipsync bank", f"not a readable .npz ({err})") from None
    analysis = (int(data["sample_rate"]), int(data["frame_length"]), int(data["lpc_order"]))
    if analysis != (SAMPLE_RATE, FRAME_LENGTH, LPC_ORDER):
        raise InputError(path, "lipsync bank", f"trained for (rate, frame, order) {analysis}, this analysis is "
                                               f"{(SAMPLE_RATE, FRAME_LENGTH, LPC_ORDER)}")
    f64 = lambda k, i: data[k][i].astype(np.float64)  # noqa: E731
    sets = tuple(MouthNet(str(name), f64("mean", i), f64("scale", i), f64("w1", i), f64("b1", i),
                          f64("w2", i), f64("b2", i)) for i, name in enumerate(data["names"]))
    return LipSyncBank(sets, tuple(str(v) for v in data["voices"]))


# -------------------------------------------------------------------------------------------- runtime

def mouth_parameters(samples, times, weights=None, silence_db=30.0):
    """Mouth parameters [mm] (N, 13) at each time [s], unsmoothed: the net's output, or the closed mouth
    where the frame is silent.

    The gate exists beside the net because the cepstrum leaves out c_0, the frame's level: a breath or the
    room between words can have an envelope that resembles a vowel, and only its loudness says it is not
    speech. A frame is silent when it is more than `silence_db` below the loudest frame of the clip, or below
    -60 dBFS outright."""
    weights = load_bank().general if weights is None else weights
    samples = np.asarray(samples, np.float64)
    times = np.atleast_1d(np.asarray(times, np.float64))
    params = weights(cepstra(samples, times))
    energy = frame_energy_db(samples, times)
    loudest = frame_energy_db(samples, frame_times(samples, FRAME_SECONDS / 4)).max() if samples.size else -200.0
    silent = (energy < loudest - silence_db) | (energy < -60.0)
    params[silent] = VOWEL_SHAPES[CLOSED]
    return params


def animation_frame_count(num_samples, fps):
    """Frames 0..T-1 at `fps` whose times i / fps cover the audio: T = ceil(duration * fps)."""
    return max(1, int(math.ceil(num_samples * fps / SAMPLE_RATE - 1e-9)))


def mouth_track(samples, fps, weights=None, smoothing=0.03, silence_db=30.0):
    """Mouth parameters [mm] (T, 13) for animation frames i = 0..T-1 at times i / fps covering 16 kHz audio.

    `smoothing` is the standard deviation [s] of a zero-phase Gaussian over the frames: it keeps the mouth
    from chattering between neighbouring vowels and eases it open and shut; 0 turns it off."""
    if fps <= 0:
        raise ValueError(f"fps must be positive, got {fps}")
    times = np.arange(animation_frame_count(len(samples), fps)) / float(fps)
    params = mouth_parameters(samples, times, weights, silence_db)
    sigma = smoothing * fps
    if sigma >= 0.25 and len(times) > 1:
        params = gaussian_filter1d(params, sigma, axis=0, mode="nearest")
    return params


def classify(params):
    """Index into sim.mouth.VOWELS of the base nearest to each parameter vector (..., 13)."""
    return nearest_vowel(params)


class Adaptation(NamedTuple):
    """The weight set chosen for a speaker and how well each set reproduced the speaker's vowels."""

    weights: MouthNet
    index: int  # into bank.sets
    error_mm: float  # RMS distance of the chosen set's outputs from the vowel shapes
    errors_mm: np.ndarray  # (len(bank.sets),) the same for every set


def steady_times(samples, hop=0.01, within_db=10.0):
    """Frame centres [s] where a held vowel is steady: within `within_db` of the clip's loudest frame."""
    times = frame_times(samples, hop)
    energy = frame_energy_db(samples, times)
    return times[energy >= energy.max() - within_db]


def choose_weights(bank, vowel_audio):
    """Speaker adaptation, Yotsukura et al. §4.1: run every set in the bank on the speaker's five vowels and
    keep the one whose outputs lie closest to the vowel shapes.

    `vowel_audio` maps 'a', 'i', 'u', 'e', 'o' to 16 kHz samples of the speaker holding that vowel. Each
    vowel counts equally, however long it was held."""
    missing = [v for v in SPOKEN_VOWELS if v not in vowel_audio]
    if missing:
        raise ValueError(f"speaker adaptation needs all five vowels; missing {', '.join(missing)}")
    sq = np.zeros(len(bank.sets))
    for vowel in SPOKEN_VOWELS:
        samples = np.asarray(vowel_audio[vowel], np.float64)
        c = cepstra(samples, steady_times(samples))
        target = VOWEL_SHAPES[VOWELS.index(vowel)]
        for i, net in enumerate(bank.sets):
            sq[i] += np.mean(np.sum((net(c) - target) ** 2, axis=1)) / len(SPOKEN_VOWELS)
    errors = np.sqrt(sq / NUM_MOUTH_PARAMETERS)
    best = int(np.argmin(errors))
    return Adaptation(bank.sets[best], best, float(errors[best]), errors)


# ---------------------------------------------------------------------------------- synthetic speech

def espeak_available():
    return shutil.which("espeak-ng") is not None


def speak(text, voice, pitch=50, speed=175):
    """Speech from the espeak-ng synthesiser as 16 kHz float samples. `text` may hold phonemes in [[ ]]."""
    exe = shutil.which("espeak-ng")
    if exe is None:
        raise RuntimeError("espeak-ng is not installed (Debian/Ubuntu: apt-get install espeak-ng)")
    with tempfile.TemporaryDirectory() as tmp:
        wav = os.path.join(tmp, "speech.wav")
        subprocess.run([exe, "-v", voice, "-p", str(int(pitch)), "-s", str(int(speed)), "-w", wav, text],
                       check=True, capture_output=True)
        return load_audio(wav)


def vowel_clip(vowel, voice, pitch=50, speed=TRAINING_SPEED, lead=0.25, tail=0.25):
    """A held Japanese vowel from espeak-ng with `lead` and `tail` seconds of digital silence around it, and
    the sample range [start, stop) where the voice is."""
    voiced = speak(f"[[{vowel}:]]", voice, pitch, speed)
    nonzero = np.flatnonzero(np.abs(voiced) > 1e-4)
    voiced = voiced[:nonzero[-1] + 1] if nonzero.size else voiced
    pad_a, pad_b = int(lead * SAMPLE_RATE), int(tail * SAMPLE_RATE)
    clip = np.concatenate([np.zeros(pad_a), voiced, np.zeros(pad_b)])
    return clip, (pad_a, pad_a + len(voiced))


def labelled_frames(clip, voiced_range, vowel, hop=0.01, edge=0.08):
    """Times [s] and VOWELS indices of a vowel clip's labelled frames: the vowel where it is steady (voiced,
    `edge` seconds in from either end), 'closed' where the 32 ms window sees no voice; transitions are left
    out."""
    times = frame_times(clip, hop)
    start, stop = voiced_range
    centre = np.round(times * SAMPLE_RATE)
    half = FRAME_LENGTH // 2
    silent = (centre + half <= start) | (centre - half >= stop)
    energy = frame_energy_db(clip, times)
    loud = np.flatnonzero(energy >= energy.max() - 20.0)
    t0, t1 = times[loud[0]] + edge, times[loud[-1]] - edge
    steady = (times >= t0) & (times <= t1)
    labels = np.where(steady, VOWELS.index(vowel), CLOSED)
    keep = steady | silent
    return times[keep], labels[keep]


def _room_noise(n, rng):
    """Quiet room: white noise at a level drawn between -70 and -45 dBFS."""
    level = 10.0 ** (rng.uniform(-70.0, -45.0) / 20.0)
    return level * rng.standard_normal(n)


def _tilted(clip, rng):
    """The clip through a one-pole filter of random slope, at the same peak level.

    Voices and microphones differ in spectral slope (breathy or pressed voice, a dull or bright microphone),
    which moves the low cepstral coefficients without changing the vowel; a dozen synthetic voices span
    little of it, so every clip is also heard tilted."""
    from scipy.signal import lfilter  # training only: kept out of every run's start-up

    beta = rng.uniform(-0.4, 0.7)
    out = lfilter([1.0], [1.0, -beta], clip)
    return out * (np.abs(clip).max() / max(np.abs(out).max(), 1e-12))


def voice_corpus(voice, pitches=TRAINING_PITCHES, speed=TRAINING_SPEED, tilts=2, hop=0.02, seed=0):
    """Cepstra (N, 20) and VOWELS labels (N,) of one voice holding each vowel at each pitch, in room noise,
    as synthesised and through `tilts` random spectral tilts."""
    rng = np.random.default_rng(seed)
    feats, labels = [], []
    for pitch in pitches:
        for vowel in SPOKEN_VOWELS:
            clean, voiced = vowel_clip(vowel, voice, pitch, speed)
            for k in range(tilts + 1):
                clip = (_tilted(clean, rng) if k else clean) + _room_noise(len(clean), rng)
                times, lab = labelled_frames(clip, voiced, vowel, hop)
                feats.append(cepstra(clip, times))
                labels.append(lab)
    return np.concatenate(feats), np.concatenate(labels)


def _class_weights(labels):
    """Each of the six classes carries the same total weight, however many frames it has."""
    counts = np.bincount(labels, minlength=len(VOWELS)).astype(np.float64)
    return 1.0 / counts[labels]


def train_bank(voices=TRAINING_VOICES, pitches=TRAINING_PITCHES, speed=TRAINING_SPEED, seed=0, log=None):
    """Synthesise every voice's vowels with espeak-ng and train one set per voice plus the general set."""
    corpora = []
    for i, voice in enumerate(voices):
        corpora.append(voice_corpus(voice, pitches, speed, seed=seed + i))
    sets = []
    for voice, (x, labels) in zip(voices, corpora):
        net = train_net(x, VOWEL_SHAPES[labels], voice, _class_weights(labels), seed=seed)
        sets.append(net)
        if log:
            log(f"{voice}: {len(x)} frames, training accuracy {np.mean(classify(net(x)) == labels):.3f}")
    x = np.concatenate([c[0] for c in corpora])
    labels = np.concatenate([c[1] for c in corpora])
    general = train_net(x, VOWEL_SHAPES[labels], "general", _class_weights(labels), seed=seed)
    sets.append(general)
    if log:
        log(f"general: {len(x)} frames, training accuracy {np.mean(classify(general(x)) == labels):.3f}")
    return LipSyncBank(tuple(sets), tuple(voices))


def make_demo_line(path, text=DEMO_LINE, voice=DEMO_VOICE, pitch=50, speed=175):
    """The built-in character's line: espeak-ng speech, 16 kHz mono 16-bit, trimmed to 0.1 s of lead-in."""
    samples = speak(text, voice, pitch, speed)
    nonzero = np.flatnonzero(np.abs(samples) > 1e-4)
    lead = int(0.1 * SAMPLE_RATE)
    samples = np.concatenate([np.zeros(lead), samples[nonzero[0]:nonzero[-1] + 1], np.zeros(lead)])
    write_wav(path, samples)
    return samples


def main(argv=None):
    parser = argparse.ArgumentParser(prog="python -m sim.lipsync", description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("train", help="synthesise the training voices with espeak-ng and write the weight bank")
    p.add_argument("-o", "--output", default=str(BANK_PATH))
    p.add_argument("--seed", type=int, default=0)
    p = sub.add_parser("demo-line", help="speak the built-in character's line with espeak-ng to a 16 kHz WAV")
    p.add_argument("-o", "--output", default=str(DEMO_LINE_PATH))
    args = parser.parse_args(argv)
    log = lambda msg: print(msg, file=sys.stderr)  # noqa: E731
    Path(args.output).parent.mkdir(parents=True, exist_ok=True)
    if args.command == "train":
        bank = train_bank(seed=args.seed, log=log)
        bank.save(args.output)
        log(f"wrote {args.output}: {len(bank.sets)} weight sets ({', '.join(bank.names)})")
    else:
        samples = make_demo_line(args.output)
        log(f"wrote {args.output}: {len(samples) / SAMPLE_RATE:.2f} s at {SAMPLE_RATE} Hz")
    return 0


if __name__ == "__main__":
    sys.exit(main())
