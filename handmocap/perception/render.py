"""A small offscreen mesh renderer: OpenGL through moderngl, headless via EGL.

Camera model: OpenCV pinhole (x right, y down, z forward, metres), intrinsics K
(fx, fy, cx, cy in pixels, pixel centres at integer coordinates), no distortion.
Meshes are given in that camera frame. Shading: Lambert diffuse plus Blinn-Phong
specular from a head light and a key light, both sides of each triangle lit (a cropped
forearm or a mirrored mesh still looks solid). Returns RGB (H,W,3) uint8 and depth
(H,W) float32 = camera z in metres, 0 where no surface.

Needs the optional `moderngl` package and an EGL driver (on Debian/Ubuntu:
libegl1 libgl1-mesa-dri libegl-mesa0; Mesa's llvmpipe renders without a GPU).
"""
import numpy as np

_VERTEX_SHADER = """
#version 330
uniform mat4 proj;
in vec3 in_pos;
in vec3 in_normal;
in vec3 in_color;
out vec3 v_pos;
out vec3 v_normal;
out vec3 v_color;
void main() {
    v_pos = in_pos;
    v_normal = in_normal;
    v_color = in_color;
    gl_Position = proj * vec4(in_pos, 1.0);
}
"""

_FRAGMENT_SHADER = """
#version 330
uniform vec3 key_dir;      // direction towards the key light, camera frame
uniform float ambient;
uniform float specular;
uniform float shininess;
in vec3 v_pos;
in vec3 v_normal;
in vec3 v_color;
layout(location = 0) out vec4 out_color;
layout(location = 1) out float out_depth;
void main() {
    vec3 view = normalize(-v_pos);            // towards the camera at the origin
    vec3 n = normalize(v_normal);
    if (dot(n, view) < 0.0) n = -n;           // light both sides
    vec3 lights[2] = vec3[2](view, normalize(key_dir));
    float weights[2] = float[2](0.45, 0.55);
    vec3 rgb = ambient * v_color;
    for (int i = 0; i < 2; ++i) {
        float diffuse = max(dot(n, lights[i]), 0.0);
        vec3 h = normalize(lights[i] + view);
        float spec = diffuse > 0.0 ? pow(max(dot(n, h), 0.0), shininess) : 0.0;
        rgb += weights[i] * (diffuse * v_color + specular * spec);
    }
    out_color = vec4(clamp(rgb, 0.0, 1.0), 1.0);
    out_depth = v_pos.z;
}
"""

SKIN = (0.87, 0.68, 0.58)


def vertex_normals(vertices, faces):
    """(V,3) unit normals, area-weighted average of the adjacent faces' normals."""
    v = np.asarray(vertices, dtype=np.float64)
    tri = v[faces]
    face_n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])   # length = 2 * area
    normals = np.zeros_like(v)
    for k in range(3):
        np.add.at(normals, faces[:, k], face_n)
    return normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)


def projection_matrix(K, width, height, near, far):
    """4x4 OpenGL projection for OpenCV intrinsics K (3x3 or fx,fy,cx,cy).

    Image row v maps to framebuffer row v counted from the bottom, so the buffer read
    back row by row is already in image order (top row first).
    """
    fx, fy, cx, cy = (K[0, 0], K[1, 1], K[0, 2], K[1, 2]) if np.ndim(K) == 2 else K
    cx, cy = cx + 0.5, cy + 0.5      # OpenGL pixel centres sit at +0.5
    return np.array([
        [2 * fx / width, 0, 2 * cx / width - 1, 0],
        [0, 2 * fy / height, 2 * cy / height - 1, 0],
        [0, 0, (far + near) / (far - near), -2 * far * near / (far - near)],
        [0, 0, 1, 0],
    ])


class MeshRenderer:
    """Offscreen renderer of triangle meshes into a fixed-size image.

    >>> r = MeshRenderer(640, 480)
    >>> rgb, depth = r.render([(vertices, faces)], K)
    """

    def __init__(self, width, height, samples=4, near=0.01, far=20.0):
        import moderngl   # optional dependency, imported where it is needed
        self.width, self.height, self.near, self.far = width, height, near, far
        self.ctx = moderngl.create_standalone_context(backend="egl")
        self.program = self.ctx.program(vertex_shader=_VERTEX_SHADER, fragment_shader=_FRAGMENT_SHADER)
        samples = min(samples, self.ctx.max_samples)
        self.msaa = self.ctx.framebuffer(
            color_attachments=[self.ctx.renderbuffer((width, height), 4, samples=samples)],
            depth_attachment=self.ctx.depth_renderbuffer((width, height), samples=samples))
        self.color_fbo = self.ctx.framebuffer(color_attachments=[self.ctx.renderbuffer((width, height), 4)])
        self.depth_fbo = self.ctx.framebuffer(
            color_attachments=[self.ctx.renderbuffer((width, height), 4),
                               self.ctx.renderbuffer((width, height), 1, dtype="f4")],
            depth_attachment=self.ctx.depth_renderbuffer((width, height)))

    def render(self, meshes, K, background=(1.0, 1.0, 1.0), key_light=(-0.4, -0.6, -0.7),
               ambient=0.25, specular=0.15, shininess=24.0):
        """Draw meshes seen by the camera K.

        meshes: list of (vertices (V,3) metres in camera frame, faces (F,3)[, color]),
            color (3,) or (V,3) in [0,1] (default a skin tone).
        Returns rgb (H,W,3) uint8 and depth (H,W) float32 (camera z, 0 = background).
        """
        with self.ctx:   # several renderers in one process: draw into this one's context
            return self._render(meshes, K, key_light, background, ambient, specular, shininess)

    def _render(self, meshes, K, key_light, background, ambient, specular, shininess):
        self.program["proj"].write(projection_matrix(K, self.width, self.height, self.near, self.far)
                                   .T.astype("f4").tobytes())
        self.program["key_dir"].value = tuple(float(x) for x in key_light)
        self.program["ambient"].value = ambient
        self.program["specular"].value = specular
        self.program["shininess"].value = shininess
        vaos = []
        for mesh in meshes:
            vertices, faces = np.asarray(mesh[0], dtype=np.float64), np.asarray(mesh[1])
            color = np.asarray(mesh[2] if len(mesh) > 2 else SKIN, dtype=np.float64)
            color = np.broadcast_to(color, vertices.shape)
            data = np.concatenate([vertices, vertex_normals(vertices, faces), color], 1).astype("f4")
            vbo = self.ctx.buffer(data.tobytes())
            ibo = self.ctx.buffer(np.ascontiguousarray(faces, dtype="i4").tobytes())
            vaos.append((self.ctx.vertex_array(self.program, [(vbo, "3f 3f 3f", "in_pos", "in_normal", "in_color")],
                                               index_buffer=ibo), vbo, ibo))
        self.ctx.enable(self.ctx.DEPTH_TEST)
        # colour pass (multisampled), then a depth pass whose float target starts at 0 = nothing
        for fbo, clear in ((self.msaa, tuple(background)), (self.depth_fbo, (0.0, 0.0, 0.0))):
            fbo.use()
            fbo.clear(*clear, 1.0)
            for vao, _, _ in vaos:
                vao.render()
        self.ctx.copy_framebuffer(self.color_fbo, self.msaa)
        rgb = np.frombuffer(self.color_fbo.read(components=3), dtype=np.uint8).reshape(self.height, self.width, 3)
        depth = np.frombuffer(self.depth_fbo.read(components=1, attachment=1, dtype="f4"),
                              dtype=np.float32).reshape(self.height, self.width)
        for vao, vbo, ibo in vaos:
            vao.release(), vbo.release(), ibo.release()
        return rgb.copy(), depth.copy()

    def release(self):
        self.ctx.release()
