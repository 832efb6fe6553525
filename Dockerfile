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
COPY . /app

# constraints.txt pins torch's version. On PyPI that version is the CUDA build for Linux
# x86_64 (several GB of nvidia-* wheels), so the constraint alone is not enough: the extra
# index serves the same version as "+cpu", which satisfies the pin (a local label is ignored
# when matching ==) and sorts above the PyPI build, so pip takes the CPU wheel. pip looks at
# both indexes for every package and takes the highest version; the rest resolves as on PyPI.
RUN pip install --no-cache-dir -c constraints.txt \
        --extra-index-url https://download.pytorch.org/whl/cpu -e .

ENTRYPOINT ["forcegrasp"]
CMD ["--help"]
