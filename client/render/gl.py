"""Headless OpenGL for the render client: an EGL standalone context, reversed-Z
with a float depth buffer, and GL error checks.

The context is a moderngl standalone context on the EGL backend (no window,
no X server): Mesa's llvmpipe on machines without a GPU, the vendor's driver
where there is one. OpenGL 4.5 core is required for ``glClipControl``.

Depth: reversed-Z, float32 depth, infinite far plane. The projection maps
view depth d (metres along the optical axis) to window depth near/d
(camera.projection_reversed_z), the clip control maps NDC depth [0, 1]
straight to the depth range (no (z + 1)/2 that would round the small values
away), and the float depth buffer keeps float32's 24-bit relative precision
at every depth: two surfaces are resolved when they are about 1.2e-7 x d
apart (5 cm at 400 km, 0.1 um at 1 m). A 24-bit fixed-point buffer with the
usual near/far mapping resolves ~d^2 / (near x 2^24): 9.5 km at 400 km with a
1 m near plane. Reversed-Z keeps the fixed-function depth test and its early
rejection of hidden fragments, which matters on llvmpipe; a logarithmic depth
buffer would have to write gl_FragDepth in every fragment shader and lose it.
(Reed, "Depth Precision Visualized", NVIDIA 2015; Lapidous & Jiao, "Optimal
depth buffer for low-cost graphics hardware", Graphics Hardware 1999.)

moderngl exposes neither glClipControl nor float depth attachments, so the
two GL 4.5 entry points are called through ctypes (eglGetProcAddress):
``glClipControl`` once per context, and ``glTexImage2D`` to give moderngl's
depth texture GL_DEPTH_COMPONENT32F storage. Every GL call of a renderer must
run with its context current (``with ctx:``): a process may hold several.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging

from sortie.errors import SortieError

log = logging.getLogger(__name__)

REQUIRED_GL_VERSION = 450  # glClipControl is core in OpenGL 4.5

# GL enums (Khronos gl.xml).
_GL_LOWER_LEFT = 0x8CA1
_GL_ZERO_TO_ONE = 0x935F
_GL_TEXTURE_2D = 0x0DE1
_GL_DEPTH_COMPONENT = 0x1902
_GL_DEPTH_COMPONENT32F = 0x8CAC
_GL_FLOAT = 0x1406


class GLUnavailable(SortieError):
    """No usable OpenGL: EGL missing, no driver, or a version below 4.5."""


class GLError(SortieError):
    """OpenGL reported an error (glGetError) after an operation."""


def create_context():
    """A moderngl standalone context on EGL (headless), OpenGL >= 4.5 core.

    Raises GLUnavailable with the reason (and what to install) when there is none.
    """
    try:
        import moderngl
    except ImportError as exc:
        raise GLUnavailable(f"moderngl is not installed ({exc})") from None
    try:
        ctx = moderngl.create_standalone_context(backend="egl", require=REQUIRED_GL_VERSION)
    except Exception as exc:  # noqa: BLE001 - moderngl/glcontext raise plain Exceptions
        raise GLUnavailable(f"cannot create a headless OpenGL {REQUIRED_GL_VERSION // 100}."
                            f"{REQUIRED_GL_VERSION // 10 % 10} context through EGL: {exc} "
                            "(install libegl1 and Mesa's libgl1-mesa-dri for software rendering)") from None
    log.info("OpenGL %s on %s", ctx.info.get("GL_VERSION"), ctx.info.get("GL_RENDERER"))
    return ctx


def check_gl_error(ctx, where: str) -> None:
    """Raise GLError naming ``where`` if the context has a GL error pending."""
    err = ctx.error
    if err != "GL_NO_ERROR":
        raise GLError(f"OpenGL error after {where}: {err}")


class _GLFunctions:
    """The two GL 4.5 entry points moderngl does not wrap, looked up once per process."""

    def __init__(self):
        name = ctypes.util.find_library("EGL") or "libEGL.so.1"
        try:
            egl = ctypes.CDLL(name)
        except OSError as exc:
            raise GLUnavailable(f"cannot load {name}: {exc}") from None
        egl.eglGetProcAddress.restype = ctypes.c_void_p
        egl.eglGetProcAddress.argtypes = [ctypes.c_char_p]

        def lookup(symbol: bytes, *argtypes):
            address = egl.eglGetProcAddress(symbol)
            if not address:
                raise GLUnavailable(f"OpenGL entry point {symbol.decode()} not found (OpenGL 4.5 required)")
            return ctypes.CFUNCTYPE(None, *argtypes)(address)

        u, i = ctypes.c_uint, ctypes.c_int
        self.clip_control = lookup(b"glClipControl", u, u)
        self.bind_texture = lookup(b"glBindTexture", u, u)
        self.tex_image_2d = lookup(b"glTexImage2D", u, i, i, i, i, i, u, u, ctypes.c_void_p)


_functions: _GLFunctions | None = None


def _gl() -> _GLFunctions:
    global _functions
    if _functions is None:
        _functions = _GLFunctions()
    return _functions


def enable_reversed_z(ctx) -> None:
    """glClipControl(GL_LOWER_LEFT, GL_ZERO_TO_ONE) on ``ctx`` (current), depth test GREATER.

    Clear depth to 0.0 (infinitely far) with this mapping.
    """
    import moderngl

    _gl().clip_control(_GL_LOWER_LEFT, _GL_ZERO_TO_ONE)
    ctx.enable(moderngl.DEPTH_TEST)
    ctx.depth_func = ">"
    check_gl_error(ctx, "glClipControl")


def float_depth_texture(ctx, size: tuple[int, int]):
    """A moderngl depth texture of ``size`` (width, height) with GL_DEPTH_COMPONENT32F storage."""
    tex = ctx.depth_texture(size)
    gl = _gl()
    gl.bind_texture(_GL_TEXTURE_2D, tex.glo)
    gl.tex_image_2d(_GL_TEXTURE_2D, 0, _GL_DEPTH_COMPONENT32F, size[0], size[1], 0, _GL_DEPTH_COMPONENT, _GL_FLOAT,
                    None)
    gl.bind_texture(_GL_TEXTURE_2D, 0)
    check_gl_error(ctx, "float depth texture")
    return tex
