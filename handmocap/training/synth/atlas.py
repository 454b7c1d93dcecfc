"""Many small scenes per OpenGL pass: a texture atlas of square tiles, one viewport each.

Every tile is one image (a 128 px crop, or a whole frame) with its own camera K, lights
and materials. Hands share one vertex buffer (posed on the CPU, uploaded once per pass)
and one static attribute buffer (rest position and material weights, uploaded once);
each hand or object is one draw call into its tile's viewport. Rendering goes through
moderngl + EGL (Mesa's llvmpipe on a CPU), like handmocap.perception.render.

Outputs per tile (image order, top row first):
* rgb (T,T,3) uint8, sRGB, shaded;
* alpha (T,T) uint8: 255 where any surface was drawn (hands, objects);
* depth (T,T) float32: camera z in metres of the nearest surface, 0 where none;
* ids (T,T) uint8: what the nearest surface is, 0 none, 1 the labelled hand,
  2 the second hand, 3 an occluding object;
* parts (T,T) uint8: for hands, the joint frame that moves that surface most (an index
  into skeleton.NON_TIP_JOINTS: 0 palm and forearm, 1-15 the finger segments).

Shading (fragment shader, linear light, sRGB out): wrapped Lambert diffuse from a key and
a fill light with a red subsurface tint near the terminator (skin), hemisphere ambient
(sky / ground colours around an up vector), Blinn-Phong specular with Schlick Fresnel,
procedural skin albedo: tone, lighter palm side, darker knuckles, pinkish glossy nails,
1 mm pores and 4 mm blotches of value noise, an optional sleeve above a rest-y height.
"""
import numpy as np

from handmocap.perception.render import projection_matrix

ID_NONE, ID_HAND, ID_OTHER_HAND, ID_OBJECT = 0, 1, 2, 3

_VERTEX_SHADER = """
#version 330
uniform mat4 proj;
in vec3 in_pos;
in vec3 in_normal;
in vec3 in_rest;
in vec4 in_mat;
in float in_part;
out vec3 v_pos;
out vec3 v_normal;
out vec3 v_rest;
out vec4 v_mat;
flat out float v_part;
void main() {
    v_pos = in_pos;
    v_part = in_part;
    v_normal = in_normal;
    v_rest = in_rest;
    v_mat = in_mat;
    gl_Position = proj * vec4(in_pos, 1.0);
}
"""

# light[0] key dir, key intensity   light[1] key rgb, diffuse wrap
# light[2] fill dir, fill intensity light[3] fill rgb, exposure
# light[4] sky rgb, ambient         light[5] ground rgb, specular scale
# light[6] up dir, -
# mat[0] base albedo (linear), id   mat[1] palm albedo, specular
# mat[2] nail albedo, shininess     mat[3] sleeve albedo, sleeve rest-y threshold
# mat[4] knuckle tint, noise amp    mat[5] mode (0 skin, 1 object), pattern, frequency, contrast
# mat[6] pattern second albedo, subsurface strength
_FRAGMENT_SHADER = """
#version 330
uniform vec4 light[7];
uniform vec4 mat[7];
in vec3 v_pos;
in vec3 v_normal;
in vec3 v_rest;
in vec4 v_mat;
flat in float v_part;
layout(location = 0) out vec4 out_color;
layout(location = 1) out vec2 out_label;

float hash(vec3 p) {
    p = fract(p * 0.3183099 + vec3(0.71, 0.113, 0.419));
    p *= 17.0;
    return fract(p.x * p.y * p.z * (p.x + p.y + p.z));
}
float vnoise(vec3 x) {
    vec3 i = floor(x);
    vec3 f = fract(x);
    f = f * f * (3.0 - 2.0 * f);
    return mix(mix(mix(hash(i), hash(i + vec3(1, 0, 0)), f.x),
                   mix(hash(i + vec3(0, 1, 0)), hash(i + vec3(1, 1, 0)), f.x), f.y),
               mix(mix(hash(i + vec3(0, 0, 1)), hash(i + vec3(1, 0, 1)), f.x),
                   mix(hash(i + vec3(0, 1, 1)), hash(i + vec3(1, 1, 1)), f.x), f.y), f.z);
}

void main() {
    vec3 view = normalize(-v_pos);
    vec3 n = normalize(v_normal);
    if (dot(n, view) < 0.0) n = -n;
    vec3 albedo;
    float spec_k = mat[1].w;
    float shininess = mat[2].w;
    float wrap = light[1].w;
    float sss = mat[6].w;
    if (mat[5].x < 0.5) {                                   // skin
        float nail = v_mat.x;
        vec3 skin = mix(mat[0].rgb, mat[1].rgb, v_mat.y);
        skin = mix(skin, skin * mat[4].rgb, v_mat.z);
        float grain = 0.55 * vnoise(v_rest * 1100.0) + 0.45 * vnoise(v_rest * 260.0);
        skin *= 1.0 + mat[4].w * (grain - 0.5);
        albedo = mix(skin, mat[2].rgb, nail);
        spec_k *= 1.0 + 2.5 * nail;
        shininess *= 1.0 + 2.0 * nail;
        if (v_rest.y > mat[3].w) {                          // sleeve
            albedo = mat[3].rgb * (0.8 + 0.4 * vnoise(v_rest * 500.0));
            spec_k = 0.01; shininess = 6.0; wrap = 0.15; sss = 0.0;
        }
    } else {                                                // object
        float p = 0.0;
        vec3 q = v_rest * mat[5].z;
        if (mat[5].y > 2.5) p = vnoise(q * 0.5) > 0.5 ? 1.0 : 0.0;                    // blotches
        else if (mat[5].y > 1.5) p = mod(floor(q.x) + floor(q.y) + floor(q.z), 2.0);   // checker
        else if (mat[5].y > 0.5) p = step(0.5, fract(q.x + 0.3 * q.z));                // stripes
        albedo = mix(mat[0].rgb, mat[6].rgb, p * mat[5].w);
        albedo *= 0.9 + 0.2 * vnoise(v_rest * 300.0);
    }
    vec3 rgb = vec3(0.0);
    for (int i = 0; i < 2; ++i) {
        vec3 l = normalize(light[2 * i].xyz);
        float nl = dot(n, l);
        float diffuse = max((nl + wrap) / (1.0 + wrap), 0.0);
        vec3 tint = mix(vec3(1.0, 0.42, 0.30), vec3(1.0), mix(1.0, smoothstep(-0.2, 0.45, nl), sss));
        rgb += light[2 * i].w * light[2 * i + 1].rgb * diffuse * tint * albedo;
        vec3 h = normalize(l + view);
        float fresnel = 0.04 + 0.96 * pow(1.0 - max(dot(n, view), 0.0), 5.0);
        float spec = nl > 0.0 ? pow(max(dot(n, h), 0.0), shininess) : 0.0;
        rgb += light[2 * i].w * light[2 * i + 1].rgb * spec * spec_k * light[5].w * (0.6 + 4.0 * fresnel);
    }
    float hemi = 0.5 + 0.5 * dot(n, normalize(light[6].xyz));
    rgb += light[4].w * mix(light[5].rgb, light[4].rgb, hemi) * albedo;
    rgb *= light[3].w;
    rgb = rgb / (1.0 + 0.15 * rgb);
    out_color = vec4(pow(clamp(rgb, 0.0, 1.0), vec3(1.0 / 2.2)), 1.0);
    out_label = vec2(v_pos.z, mat[0].w * 32.0 + v_part);
}
"""


class AtlasRenderer:
    """Renders up to `capacity` tiles of `tile` x `tile` pixels per pass.

    hand: a SynthHand (its faces and static attributes). `hands_per_pass` bounds how
    many hand meshes one pass can hold (labelled hands plus second hands).
    """

    def __init__(self, hand, tile=128, capacity=None, hands_per_pass=None, near=0.01, far=20.0):
        import moderngl   # optional dependency, imported where it is needed
        self.tile = int(tile)
        self.cols = max(1, 1024 // self.tile)
        self.capacity = capacity or self.cols * self.cols
        self.rows = -(-self.capacity // self.cols)
        self.width, self.height = self.cols * self.tile, self.rows * self.tile
        self.near, self.far = near, far
        self.hand = hand
        self.hands_per_pass = hands_per_pass or 2 * self.capacity
        self.ctx = moderngl.create_standalone_context(backend="egl")
        self.program = self.ctx.program(vertex_shader=_VERTEX_SHADER, fragment_shader=_FRAGMENT_SHADER)
        size = (self.width, self.height)
        self.fbo = self.ctx.framebuffer(
            color_attachments=[self.ctx.renderbuffer(size, 4), self.ctx.renderbuffer(size, 2, dtype="f4")],
            depth_attachment=self.ctx.depth_renderbuffer(size))
        nv, nf = hand.num_vertices, len(hand.faces)
        self._hand_vertices = nv
        self._hand_indices = 3 * nf
        self.hand_dynamic = self.ctx.buffer(reserve=self.hands_per_pass * nv * 6 * 4, dynamic=True)
        static = np.concatenate([hand.v_template, hand.material, hand.part[:, None]], 1).astype("f4")
        self.hand_static = self.ctx.buffer(np.tile(static, (self.hands_per_pass, 1)).tobytes())
        offsets = (np.arange(self.hands_per_pass) * nv)[:, None, None]
        self.hand_ibo = self.ctx.buffer((hand.faces[None] + offsets).astype("i4").tobytes())
        self.hand_vao = self.ctx.vertex_array(self.program, [
            (self.hand_dynamic, "3f 3f", "in_pos", "in_normal"),
            (self.hand_static, "3f 4f 1f", "in_rest", "in_mat", "in_part")], index_buffer=self.hand_ibo)
        self._object_capacity = 0
        self.object_vbo = self.object_vao = None

    def _object_buffers(self, n_floats):
        if n_floats > self._object_capacity:
            if self.object_vao is not None:
                self.object_vao.release(), self.object_vbo.release()
            self._object_capacity = max(n_floats, 2 * self._object_capacity, 1 << 16)
            self.object_vbo = self.ctx.buffer(reserve=self._object_capacity * 4, dynamic=True)
            self.object_vao = self.ctx.vertex_array(self.program, [
                (self.object_vbo, "3f 3f 3f 4f 1f", "in_pos", "in_normal", "in_rest", "in_mat", "in_part")])

    def tile_slices(self, i):
        """(rows, cols) slices of tile i in the read-back atlas arrays."""
        r, c = divmod(i, self.cols)
        return slice(r * self.tile, (r + 1) * self.tile), slice(c * self.tile, (c + 1) * self.tile)

    def render(self, K, hand_vertices, hand_normals, hand_draws, object_triangles=(), object_draws=(),
               lights=None):
        """Draw one pass.

        K: (n,3,3) per-tile intrinsics (n <= capacity).
        hand_vertices, hand_normals: (M,V,3) camera-frame meshes (M <= hands_per_pass).
        hand_draws: list of (tile, hand index, mat (7,4), mirrored) — one draw per hand;
            mirrored (left) hands have the opposite winding, for back-face culling.
        object_triangles: (P,3,3) positions, normals, rest-coords per vertex of all objects'
            triangles, concatenated, shape (P*3, 9) floats; object_draws: list of (tile,
            first vertex, vertex count, mat (7,4)).
        lights: (n,7,4) per-tile light block.
        Returns rgb (n,T,T,3) uint8, alpha (n,T,T) uint8, depth (n,T,T) f4, ids and
        parts (n,T,T) u1.
        """
        n = len(K)
        if n > self.capacity:
            raise ValueError(f"{n} tiles > capacity {self.capacity}")
        m = len(hand_vertices)
        if m > self.hands_per_pass:
            raise ValueError(f"{m} hands > {self.hands_per_pass} per pass")
        if m:
            data = np.concatenate([hand_vertices, hand_normals], -1).astype("f4", copy=False)
            self.hand_dynamic.write(np.ascontiguousarray(data).tobytes())
        if len(object_draws):
            tri = np.asarray(object_triangles, dtype="f4")
            payload = np.concatenate([tri, np.zeros((len(tri), 5), "f4")], 1)
            self._object_buffers(payload.size)
            self.object_vbo.write(payload.tobytes())
        projections = [projection_matrix(k, self.tile, self.tile, self.near, self.far).T.astype("f4").tobytes()
                       for k in K]
        self.fbo.use()
        self.fbo.clear(0.0, 0.0, 0.0, 0.0, 1.0)
        self.ctx.enable(self.ctx.DEPTH_TEST)
        proj, light_u, mat_u = self.program["proj"], self.program["light"], self.program["mat"]
        lights = np.asarray(lights, dtype="f4")
        current = -1

        def select(tile):
            nonlocal current
            if tile != current:
                r, c = divmod(tile, self.cols)
                # GL rows count from the bottom; the read-back rows start there too
                self.fbo.viewport = (c * self.tile, r * self.tile, self.tile, self.tile)
                proj.write(projections[tile])
                light_u.write(lights[tile].tobytes())
                current = tile

        # closed meshes: cull back faces (half the triangles). The projection flips image
        # rows, so a right hand's outward faces wind clockwise in window space.
        self.ctx.enable(self.ctx.CULL_FACE)
        for tile, index, mat, mirrored in hand_draws:
            select(tile)
            self.ctx.front_face = "ccw" if mirrored else "cw"
            mat_u.write(np.asarray(mat, dtype="f4").tobytes())
            self.hand_vao.render(first=index * self._hand_indices, vertices=self._hand_indices)
        self.ctx.disable(self.ctx.CULL_FACE)
        for tile, first, count, mat in object_draws:
            select(tile)
            mat_u.write(np.asarray(mat, dtype="f4").tobytes())
            self.object_vao.render(first=first, vertices=count)
        rows = -(-n // self.cols) * self.tile
        viewport = (0, 0, self.width, rows)
        color = np.frombuffer(self.fbo.read(viewport=viewport, components=4), np.uint8).reshape(rows, self.width, 4)
        label = np.frombuffer(self.fbo.read(viewport=viewport, components=2, attachment=1, dtype="f4"),
                              np.float32).reshape(rows, self.width, 2)
        t = self.tile
        tiles = lambda a: a.reshape(rows // t, t, self.cols, t, *a.shape[2:]).swapaxes(1, 2).reshape(
            -1, t, t, *a.shape[2:])[:n]
        color, label = tiles(color), tiles(label)
        code = np.rint(label[..., 1]).astype(np.int32)
        return color[..., :3].copy(), color[..., 3].copy(), label[..., 0].copy(), (code >> 5).astype(np.uint8), \
            (code & 31).astype(np.uint8)

    def release(self):
        self.ctx.release()
