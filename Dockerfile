# ForceGrasp: one image for every service; the sub-command picks the role
# (docker run IMAGE learner | actor | evaluator | train ...). See docs/docker.md.
#
# Debian bookworm pinned: its Mesa still ships OSMesa (libosmesa6), which the
# offscreen rendering below uses, and it is the Debian release the project is tested on.
FROM python:3.11-slim-bookworm

# MuJoCo offscreen rendering on the CPU (label pictures, episode replays). Training needs
# no GL at all. OSMesa is a self-contained software renderer, so no GPU or DRI driver is
# needed; libegl1/libgl1/libopengl0 are there so MUJOCO_GL=egl works with a GPU runtime.
RUN apt-get update \
    && apt-get install -y --no-install-recommends libegl1 libgl1 libopengl0 libosmesa6 \
    && rm -rf /var/lib/apt/lists/*

ENV MUJOCO_GL=osmesa \
    PYOPENGL_PLATFORM=osmesa \
    PYTHONUNBUFFERED=1

WORKDIR /app

# Which torch: TORCH=cpu (default) or TORCH=cuda (a learner image for a GPU machine).
# constraints.txt pins torch's version. On PyPI that version is the CUDA build for Linux x86_64
# (several GB of nvidia-* wheels), so the constraint alone is not enough: the CPU index
# (TORCH_INDEX) serves the same version as "+cpu", which satisfies the pin (a local label is
# ignored when matching ==) and sorts above the PyPI build, so pip takes the CPU wheel. Where
# that index cannot be reached pip only warns and installs the CUDA build; check_torch.py then
# fails the build and says so, instead of leaving a silently 2 GB larger image.
ARG TORCH=cpu
ARG TORCH_INDEX=https://download.pytorch.org/whl/cpu
# The dependencies first, read from pyproject.toml, in a layer of their own: a change to the
# code then rebuilds in seconds instead of reinstalling torch.
COPY pyproject.toml constraints.txt /app/
COPY scripts/check_torch.py /app/scripts/
RUN if [ "$TORCH" = cpu ]; then index="--extra-index-url $TORCH_INDEX"; else index=""; fi \
    && python -c "import tomllib; print(*tomllib.load(open('pyproject.toml', 'rb'))['project']['dependencies'], sep='\n')" > /tmp/requirements.txt \
    && pip install --no-cache-dir -c constraints.txt $index -r /tmp/requirements.txt \
    && python scripts/check_torch.py "$TORCH"

COPY . /app
RUN pip install --no-cache-dir --no-deps -c constraints.txt -e . && python scripts/check_torch.py "$TORCH"

ENTRYPOINT ["forcegrasp"]
CMD ["--help"]
